"""The data sets of ``hippomap eval-vpr``: two layouts of images with ground-truth place matches.

* **VPR-Bench layout** (``DATA_DIR/ref/*.jpg``, ``DATA_DIR/query/*.jpg``,
  ``ground_truth_new.npy`` rows ``(query index, [matching reference indices])``, e.g.
  ``shared/data/corridor``): every reference image is learned as a key frame, every query
  is recognised against all of them.
* **RTAB-Map sample layout** (``DATA_DIR/data/samples/N.jpg``, ``DATA_DIR/data/samples_GT.bmp``,
  pixel (i, j) white when frame i+1 shows the place of frame j+1, e.g.
  ``shared/data/rtabmap_samples``): the first pass — the frames before the first frame that
  has a ground-truth match — is learned as the references, the second pass is queried against
  all of them; a query's positives are its ground-truth matches among the references.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError

__all__ = ["VPRDataset", "load_vpr_dataset", "read_image"]


@dataclass
class VPRDataset:
    """A place-recognition data set: reference images learned as key frames, query images recognised
    against them, and each query's positives (the indices of the references showing its place)."""

    name: str
    references: list[Path]
    queries: list[Path]
    positives: list[set[int]]  # per query: matching reference indices
    protocol: str


def _natural_key(p: Path) -> list[Any]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def _images(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".bmp", ".ppm", ".pgm")]
    return sorted(files, key=_natural_key)


def load_vpr_dataset(data_dir: str | Path) -> VPRDataset:
    """Read one of the two supported layouts (see the module docstring)."""
    root = Path(data_dir)
    if not root.is_dir():
        raise InputError(f"data directory {root} does not exist")
    if (root / "ref").is_dir() and (root / "query").is_dir():
        refs, queries = _images(root / "ref"), _images(root / "query")
        gt_path = root / "ground_truth_new.npy"
        if not gt_path.is_file():
            raise InputError(f"{gt_path} is missing")
        gt = np.load(gt_path, allow_pickle=True)
        positives: list[set[int]] = [set() for _ in queries]
        for row_no, row in enumerate(gt):
            try:
                q = int(row[0])
                refs_of_q = {int(r) for r in np.atleast_1d(row[1])}
            except (TypeError, ValueError, IndexError):
                raise InputError(
                    f"{gt_path}: row {row_no} is not (query index, [reference indices]): {row!r}"
                ) from None
            if not 0 <= q < len(queries) or any(not 0 <= r < len(refs) for r in refs_of_q):
                raise InputError(f"{gt_path}: row {row_no} names an image outside the folders: {row!r}")
            positives[q] |= refs_of_q
        protocol = (
            f"learn all {len(refs)} images of ref/ as key frames; query each of the {len(queries)} images of "
            "query/ against all of them; positives from ground_truth_new.npy"
        )
        return VPRDataset(root.name, refs, queries, positives, protocol)
    samples = root / "data" / "samples"
    gt_path = root / "data" / "samples_GT.bmp"
    if samples.is_dir() and gt_path.is_file():
        files = _images(samples)
        gt = cv2.imread(str(gt_path), cv2.IMREAD_GRAYSCALE)
        if gt is None or gt.shape != (len(files), len(files)):
            raise InputError(
                f"{gt_path} must be a {len(files)}x{len(files)} image, got {None if gt is None else gt.shape}"
            )
        truth = gt > 127
        rows = np.flatnonzero(truth.any(axis=1))
        if rows.size == 0:
            raise InputError(f"{gt_path} has no loop closure")
        split = int(rows[0])  # the first frame that revisits an earlier one starts the query pass
        refs, queries = files[:split], files[split:]
        positives = [set(int(j) for j in np.flatnonzero(truth[split + i, :split])) for i in range(len(queries))]
        protocol = (
            f"learn frames 1-{split} (the first pass, before the first ground-truth loop closure) "
            "as key frames; "
            f"query frames {split + 1}-{len(files)} against all of them; positives = white pixels of "
            "samples_GT.bmp among the references"
        )
        return VPRDataset(root.name, refs, queries, positives, protocol)
    raise InputError(
        f"{root}: not a known VPR layout (need ref/ + query/ + ground_truth_new.npy, "
        "or data/samples/ + data/samples_GT.bmp)"
    )


def read_image(path: Path) -> np.ndarray:
    """A colour image from ``path``; an InputError names a file OpenCV cannot read."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"cannot read image {path}")
    return img
