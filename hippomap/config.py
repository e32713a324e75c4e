"""Every model parameter of hippomap, in one pydantic config.

Each field carries its default and, in its description, the source of that default:
``[S]`` the paper (*A Map Construction Method Based on the Cognitive Mechanism of Rat Brain
Hippocampus*), ``[BBc]`` Bicanski & Burgess' code, ``[ORS]`` OpenRatSLAM, or ``spec`` for a
decision of the project's model specification; ``ours`` marks a choice made (and measured) by
this project, explained in ``docs/MODEL.md``.

Units: metres and radians for space, pixels for images, seconds for time.
The config is immutable (``frozen``); build a changed copy with ``model_copy(update=...)``
or validate a nested override dict with :func:`HippomapConfig.with_overrides`.

One module on purpose: a user or maintainer finds every parameter, its default and its source
in one place, section by section (spatial, visual, map, mapper); splitting the sections apart
would scatter exactly what this module exists to gather.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

_Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
_Count = Annotated[int, Field(ge=1)]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class SpatialConfig(_Frozen):
    """Grid cells -> place cells (paper §2.3, §2.4; spec §3)."""

    area_size_m: float = Field(0.40, gt=0, description="L = D, side of the local coding area: 40 cm x 40 cm [S §3.1]")
    resolution_m: float = Field(0.0005, gt=0, description="delta, place-matrix cell size: 0.05 cm [spec §3]")
    n_modules: int = Field(8, ge=1, description="grid-cell modules [S §3.1]")
    cells_per_module: int = Field(4, ge=1, description="cells per module, each with its own phase r0 [spec §3]")
    spacing_min_m: float = Field(0.005, gt=0, description="lambda lower bound 0.5 cm [S §3.1]")
    spacing_max_m: float = Field(0.02, gt=0, description="lambda upper bound 2 cm [S §3.1]")
    g_max: float = Field(1.0, gt=0, description="peak firing rate g_max of Eq. 6 [spec §5]")
    window: float = Field(
        0.1, gt=0, description="Delta T, window-comparator width as a fraction of g_max, Eq. 9 [spec §3, T]"
    )
    variance_threshold_m2: float = Field(
        1e-6, gt=0, description="T_s, the single-field variance stop test: 0.01 cm^2 = 1e-6 m^2 [spec §3]"
    )
    rate_noise: float = Field(
        0.0, ge=0, description="sigma_T, noise on the current discharge T (x g_max); keep window/2 >= 3 sigma [spec §3]"
    )
    seed: int = Field(0, description="seed for lambda, theta, r0 of the grid cells [ours: reproducible sessions]")
    iteration_order: Literal["narrowest_first", "cyclic"] = Field(
        "narrowest_first",
        description="order of the MB_n in Eq. 10: fewest window hits first, or cell index order n = 1, 2, ... "
        "cycling through the modules as in [S] Eq. 10 [ours: narrowest_first, measured in bench/bench_spatial.py]",
    )

    @model_validator(mode="after")
    def _check(self) -> "SpatialConfig":
        if self.spacing_min_m > self.spacing_max_m:
            raise ValueError("spacing_min_m must not exceed spacing_max_m")
        if self.resolution_m * 4 > self.area_size_m:
            raise ValueError("resolution_m is too coarse for area_size_m")
        if self.rate_noise > 0 and self.window / 2 < 3 * self.rate_noise:
            raise ValueError("window/2 must be >= 3 * rate_noise, or the iteration loses the true cell [spec §3]")
        return self


class VisualConfig(_Frozen):
    """Visual grid cells and the visual recognition memory (paper §2.2; spec §1-2)."""

    vgc_frequencies: tuple[float, ...] = Field(
        (0.0014, 0.002, 0.0028, 0.004, 0.0055, 0.0077, 0.0108, 0.0151, 0.0211),
        description="f_m, cycles/px of the 9 visual grid-cell modules (ratio ~sqrt 2) [BBc]",
    )
    vgc_offsets_per_axis: int = Field(10, ge=2, description="10 x 10 = 100 offsets per module [S], [BBc]")
    vgc_orientation: float = Field(0.0, description="psi_m, common module orientation [BBc]")
    fovea: int = Field(31, ge=5, description="fovea side 2h+1: 31 for <= 320 px frames (61 for 440 px) [BBc]")
    working_width: int = Field(
        320, ge=32, description="frames are resized to this width before learning/recognition [ours: fovea scale]"
    )
    sensory_sigma: float = Field(10.0, gt=0, description="sigma_SC, sensory tuning exp(-((I-v)/10)^2) [BBc]")
    sensory_cutoff: float = Field(0.01, ge=0, description="sensory sparseness cutoff [BBc]")
    blur: int = Field(3, ge=1, description="box blur of the learned image: 5 (3 for small images) [BBc]")
    n_fixations: int = Field(9, ge=3, description="N_f, fixation points learned per frame [BBc]")
    fixation_mode: Literal["corners", "random"] = Field(
        "corners", description="top-K Shi-Tomasi corners, or random points as in [S] [spec §6.1]"
    )
    min_fixations: int = Field(3, ge=1, description="skip a frame with fewer corners [spec §2]")
    n_std: float = Field(
        3.3,
        ge=0,
        description="N_std, FLC pruning threshold (0.8 for 10 images, 2.8 for 99) [BBc]; at scale the survivors are "
        "capped by max_survivors instead of raising it (spec §6.4). 3.3 with the retina front end: contrast-normalised "
        "patches are more alike than grey-level ones, so the evidence test must be stricter "
        "(eval-vpr, both sets) [ours]",
    )
    max_survivors: int = Field(
        5,
        ge=0,
        description="at most this many FLCs survive the N_std pruning (the strongest); 0 = no cap "
        "[spec §6.4: 'tune N_std so that 1-5 FLCs survive'; a cap keeps that true at any library size, ours]",
    )
    kappa: float = Field(0.4, gt=0, description="FLC -> frame gain [BBc]")
    weight_jitter: float = Field(0.1, ge=0, description="W_FLC->ID = 1 - U(0, jitter) [BBc]")
    prediction_bias: float = Field(2.0, ge=1, description="bias on the predicted FLC [BBc]")
    decision_threshold: float = Field(0.9, gt=0, le=1, description="theta_dec, frame accepted above it [S §3.2], [BBc]")
    tolerance_px: int = Field(
        8,
        ge=0,
        description="tol, vector tolerance and microsaccade radius: [BBc] 4; 8 for revisits from another "
        "viewpoint [ours]. 10 recalled slightly more on eval-vpr (rtabmap 0.83 vs 0.82, corridor 0.03 vs 0.01, with "
        "verify_saccades 1) but let a recognition >= 2 m from the truth into a simulated mapper run",
    )
    microsaccade_gain: float = Field(
        0.0,
        ge=0,
        le=1,
        description="the microsaccade's search radius grows by this fraction of the saccade's "
        "amplitude (tolerance_px + gain x |d|, searched coarse to fine): saccadic endpoint scatter grows with "
        "amplitude, and a step towards or away from the scene scales every vector between features. Off (0) by "
        "default: 0.1 raised rtabmap_samples recall (3 seeds, mean 0.811 -> 0.848, no false match) but let 1 false "
        "match through on corridor over 3 seeds (docs/MODEL.md item 15c) [ours]",
    )
    max_prediction_errors: int = Field(2, ge=0, description="reset when wrong predictions exceed it [BBc]")
    max_total_activity: float = Field(5.0, gt=0, description="reset if sum of frame activity exceeds it [BBc]")
    max_resets: int = Field(
        7,
        ge=0,
        description="resets before rejecting ('no match'); [BBc] 10. 7 chosen among 5 / 7 / 10 on the simulated "
        "tuning runs: maps as with 10 (the Bicocca world's 16 seeds sum 19.50 -> 19.28 m, 0 false closures used "
        "either way; 5: 20.36 m), rtabmap_samples recall unchanged, a rejected recognition's fixations cut by "
        "up to a third (docs/MODEL.md item 46) [ours]",
    )
    give_up_attempts: int | None = Field(
        4,
        ge=1,
        description="a recognition gives up after this many attempts when no frame's activity has reached "
        "give_up_evidence in any of them (an evidence-accumulation bound that collapses with time: nothing is "
        "building up, so further start points are unlikely to find the place); None = always use max_resets. "
        "4 chosen on the simulated tuning runs: loops and corridors unchanged, the Bicocca world's 16 tuning "
        "seeds median 2.06 -> 1.52 m with fewer false closures used, eval-vpr unchanged (docs/MODEL.md item 46) [ours]",
    )
    repeat_accept: int | None = Field(
        3,
        ge=1,
        description="accept a frame that crossed decision_threshold in this many attempts of one recognition, each "
        "reset before its verify_saccades were done (a view from a step aside keeps reaching the right frame and "
        "missing the same far prediction); not a primed frame, whose head start makes it cross again and again. 3 "
        "(the first tried): on the 64 simulated choosing runs maps summed 22.180 -> 21.843 m with 0.93 x the "
        "fixations; eval-vpr rtabmap_samples 0.818 -> 0.841, corridor 0.000 -> 0.009, no false positive; held-out "
        "seed 300 6.531 -> 3.615 m, six of its 12 small worlds 9-66 mm worse. None = never (the model before) "
        "[ours, docs/MODEL.md item 127]",
    )
    place_accept: int | None = Field(
        None,
        ge=1,
        description="a recognition about to end without a frame accepts its place once frames learned within "
        "place_span of each other have crossed decision_threshold in this many of its attempts, each reset before "
        "its verify_saccades were done: the most active crossing's frame (key frames learned one after the other "
        "are views of one stretch of the route, and a view between two of them splits its evidence); "
        "Recognition.reason says 'accepted by its place'. Off by default: with 2, eval-vpr rtabmap_samples 0.841 -> "
        "0.886 and corridor 0.009 -> 0.018 with no false positive, but on the 64 simulated choosing runs maps "
        "summed 21.843 -> 22.130 m and accepted false closures 4 -> 11. None = never [ours, docs/MODEL.md item 128]",
    )
    place_look: int | None = Field(
        None,
        ge=1,
        description="once frames learned within place_span of each other have crossed decision_threshold in "
        "place_look_crossings attempts of a recognition, each reset before its verify_saccades were done, its next "
        "attempts (at most this many, within max_resets) are made among those frames alone, each accepting only a "
        "frame verified as usual; Recognition.reason says 'accepted among its place's frames'. Off by default: "
        "with 3, eval-vpr rtabmap_samples 0.841 -> 0.864 and corridor 0.009 -> 0.009 with no false positive, but "
        "the Bicocca world's maps 1-3 % worse (64 choosing runs 21.843 -> 22.092 m; held out, seeds 309-311, "
        "8.150 -> 8.312 m, the small worlds better). None = never "
        "[ours, docs/MODEL.md item 129]",
    )
    place_look_crossings: int = Field(
        2, ge=1, description="crossings of a place's frames that make place_look look at them alone [ours]"
    )
    place_look_distinct: int = Field(
        2,
        ge=1,
        description="of the crossings that make place_look look at a place, at least this many of different frames "
        "(one frame crossing again and again is repeat_accept's case): with 1, corridor's one recognised query is "
        "lost to a look [ours, docs/MODEL.md item 129]",
    )
    place_span: int = Field(
        2,
        ge=0,
        description="frames learned within this many of each other are one place for place_accept and "
        "place_look [ours]",
    )
    place_confirmed: int = Field(
        2,
        ge=0,
        description="a crossing counts for place_accept and place_look only when its attempt had confirmed this many "
        "predictions: of 300 scenes never learned, 12 were accepted with 1, 3 with 2, 1 with 3 (1 without "
        "place_accept), and 3 loses eval-vpr's gain [ours, docs/MODEL.md item 128]",
    )
    give_up_late_attempts: int | None = Field(
        5,
        ge=1,
        description="a recognition also gives up after this many attempts when no frame's activity has crossed "
        "decision_threshold in any of them: the bar of give_up_attempts rises to the decision threshold later on "
        "(the same bound, collapsing further with time); None = never. 5 chosen among 5 / 6 / None on the 64 "
        "simulated choosing runs: 0.88 x the fixations, map ATE sum 22.854 -> 22.727 m, revisits closed 255 -> 259, "
        "no false closure used; simulated place-recognition sets 0.88 x the fixations at the same precision "
        "(docs/MODEL.md item 109) [ours]",
    )
    give_up_evidence: float = Field(
        0.5,
        gt=0,
        le=1,
        description="the frame activity one of the first give_up_attempts attempts must reach for the "
        "recognition to go on ([BBc]'s threshold is 0.9; the attempts that later accept mostly pass 0.5 early) [ours]",
    )
    give_up_frames: tuple[_Count, _Count] | None = Field(
        None,
        description="(n0, n1): the give-up bar grows with the number of frames competing in a recognition, from "
        "give_up_evidence at n0 frames or fewer, with the logarithm of the count, to decision_threshold at n1 or more "
        "(chance alone lifts the best of many frames higher); None = give_up_evidence whatever the count. A bar passed "
        "to recognise() replaces it. Off by default: (40, 320) cut the Bicocca world's fixations by 7 % with loops and "
        "corridors unchanged, but its held-out maps were no better and one kept a false closure 2.7 m apart "
        "(docs/MODEL.md item 70) [ours]",
    )
    max_saccades: int = Field(18, ge=1, description="saccades per attempt, 2 N_f [spec decision]")
    next_target: Literal["stochastic", "most_active", "nearest"] = Field(
        "nearest",
        description="[BBc] stochastic choice over all frames, [S] a random feature of the most active frame "
        "[spec §6.3], or the most active frame's unvisited feature nearest the gaze [ours, default: short saccades "
        "keep the viewpoint error of the predicted position small]",
    )
    seed: int = Field(0, description="seed for fixation order, weight jitter and random saccade/start choices [ours]")
    contrast_clip: float = Field(0.01, ge=0, lt=0.5, description="imadjust: fraction saturated in each tail [BBc]")
    retina_mode: Literal["dog", "none"] = Field(
        "dog",
        description="front end of the sensory cells (hippomap.retina): 'dog' = light adaptation, "
        "centre-surround (difference of Gaussians) and divisive contrast normalisation, so sensory cells tune to local "
        "contrast and survive lighting change; 'none' = grey levels stretched by imadjust as in [S]/[BBc] [ours]",
    )
    retina_center_sigma: float = Field(
        2.0, ge=0, description="ganglion receptive-field centre sigma, working px [ours]"
    )
    retina_surround_sigma: float = Field(
        6.0, gt=0, description="ganglion receptive-field surround sigma, working px [ours]"
    )
    retina_norm_sigma: float = Field(
        8.0, gt=0, description="pool of the divisive contrast normalisation, working px [ours]"
    )
    retina_semisaturation: float = Field(
        0.5,
        ge=0,
        description="semi-saturation constant of the normalisation as a fraction of the frame's median "
        "local contrast: keeps flat, noisy regions near zero [ours]",
    )
    retina_gain: float = Field(1.0, gt=0, description="gain of the tanh that codes the response as a grey level [ours]")
    v1_orientations: int = Field(
        0,
        ge=0,
        le=16,
        description="V1 complex-cell orientation channels beside the centre-surround one "
        "(hippomap.retina; 0 = off): the sensory cells also tune to local oriented edge energy. Off by default: 4 "
        "channels cost precision on both eval-vpr sets (3 and 4 false matches over 3 seeds), 1.7-1.9x the recognition "
        "time, and map ATE on the simulated loop (0.416 -> 0.452 m, seed 1); docs/MODEL.md item 15b [ours]",
    )
    v1_sigma: float = Field(
        1.0, ge=0, description="scale of the V1 simple cells' derivative filters, working px [ours]"
    )
    v1_pool_sigma: float = Field(
        2.0, gt=0, description="complex-cell pooling of the squared simple cells, working px [ours]"
    )
    v1_norm_sigma: float = Field(
        8.0, gt=0, description="normalisation pool of the orientation energy, working px [ours]"
    )
    v1_semisaturation: float = Field(
        0.5,
        ge=0,
        description="semi-saturation of the orientation normalisation, fraction of the frame's median "
        "pooled energy [ours]",
    )
    v1_gain: float = Field(1.0, gt=0, description="gain of the tanh coding an orientation response as a rate [ours]")
    v1_stride: int = Field(
        2,
        ge=1,
        description="the orientation channels are sampled every v1_stride px inside the fovea (complex cells "
        "are pooled, so coarser sampling loses little and keeps the drive cost down) [ours]",
    )
    corner_source: Literal["gray", "retina"] = Field(
        "gray",
        description="image whose Shi-Tomasi corners become fixation points: the contrast-stretched grey image "
        "or the retina's output; corners of the retina image are noise-amplified (rtabmap recall 0.42) [ours]",
    )
    corner_quality: float = Field(0.01, gt=0, le=1, description="Shi-Tomasi quality level of fixation points [ours]")
    corner_block: int = Field(3, ge=3, description="Shi-Tomasi block size [ours]")
    min_distance: int = Field(0, ge=0, description="min separation of fixation points; 0 = h, half the fovea [spec §2]")
    query_keypoints: int = Field(27, ge=1, description="corners of a query frame usable as first fixations [spec §6.2]")
    query_blur: bool = Field(False, description="blur the query like the learned image before sensing [ours]")
    anchor: Literal["start", "none"] = Field(
        "start",
        description="'start': the grid code re-anchors on the first matched feature (BB's global remapping for "
        "shifted stimuli) and snaps to each predicted feature; 'none': absolute image coordinates [spec §2] [ours]",
    )
    decoder: Literal["phase", "svc"] = Field(
        "phase", description="saccade decoder: phase unwrapping (spec §1 B) or spatial view cells (C)"
    )
    svc_stride: int = Field(
        4, ge=1, description="spacing of spatial view cells in working px [spec §2: 1-2; ours 4 for memory]"
    )
    softmax_gain: float = Field(1.0, gt=0, description="gain of the softmax over surviving FLCs [BBc: 1]")
    index_side: int = Field(
        8, ge=2, description="side of the area-averaged patch descriptor used by the FLC index [ours]"
    )
    index_shortlist: int = Field(64, ge=1, description="FLCs scored exactly per fixation when the index is used [ours]")
    stats_sample: int = Field(128, ge=8, description="FLCs sampled to estimate mean/sd of the drive for N_std [ours]")
    stats_stride: int = Field(
        2,
        ge=1,
        description="the statistics sample's drive is summed over every stats_stride-th row and column of its "
        "fovea (its normaliser over the same pixels); the exactly scored units keep every pixel. The drive of a "
        "blurred patch varies smoothly from pixel to pixel, so at 2 the N_std threshold's estimate is as close "
        "to the whole library's as with every pixel, at a quarter of the sample's cost (3 and 4 widen the "
        "estimated spread). 1 = every pixel [ours, docs/MODEL.md item 106]",
    )
    target_candidates: int = Field(
        16, ge=1, description="next-target candidates tried per saccade, best first (tolerance / image checks) [ours]"
    )
    trace_hypotheses: int = Field(5, ge=1, description="leading frame hypotheses recorded per trace step [ours]")
    prediction_tolerance: float = Field(
        0.9,
        gt=0,
        le=1,
        description="a prediction is confirmed when the predicted FLC's drive is >= this fraction of the best drive "
        "(1 = it must be the winner, [BBc]); < 1 because neighbouring key frames store the same physical "
        "feature [ours]",
    )
    update_on_mismatch: bool = Field(
        True,
        description="a fixation whose winner is not the predicted feature still updates the frames [BBc]; "
        "False: only the first fixation and confirmed predictions add evidence [ours]",
    )
    start_order: Literal["random", "strongest"] = Field(
        "strongest",
        description="first fixation of each attempt: a random unused query corner [spec §6.2] or the "
        "strongest unused one [ours]",
    )
    verify_saccades: int = Field(
        2,
        ge=0,
        description="after the threshold, the accepted frame must predict this many more features correctly "
        "([S] §3.2: 'once ... the recognition threshold [is reached], it will continue to scan'); a failure resets. "
        "[BBc] has none (0); 2 gave 100 % precision on both eval-vpr sets over 5 seeds, and no recognition >= 2 m from "
        "the truth in simulated mapper runs (1 + verify_per_reset 0.5 recalled as much on eval-vpr but let such "
        "near misses through) [ours]",
    )
    verify_per_reset: float = Field(
        0.0,
        ge=0,
        description="extra verification saccades per reset before the accepting attempt (floor of resets x "
        "this): each new attempt is one more chance for a wrong frame to pass, so later attempts may be made to verify "
        "more; 0 = off [ours]",
    )
    out_of_view: Literal["reset", "skip"] = Field(
        "reset",
        description="a saccade whose fovea leaves the frame resets the attempt [BBc] or picks another feature [ours]",
    )

    @model_validator(mode="after")
    def _check(self) -> "VisualConfig":
        if self.give_up_frames is not None and not self.give_up_frames[0] < self.give_up_frames[1]:
            raise ValueError(f"give_up_frames must be (n0, n1) with n0 < n1, got {self.give_up_frames}")
        return self


class MapConfig(_Frozen):
    """Cognitive map: nodes, links, loop closure, relaxation, pruning (paper §2.4; spec §4)."""

    mu_p: float = Field(1.0, gt=0, description="mu_p of Eq. 13, per metre [spec §5]")
    node_spacing_m: float = Field(
        0.25, gt=0, description="S_th, place-code distance that creates a node (Eq. 12-13) [spec §5]"
    )
    loop_radius_m: float = Field(3.0, gt=0, description="S_loop, place-code radius of the visual check [spec §5]")
    loop_transform_radius_m: float = Field(
        0.3,
        gt=0,
        description="gate base for a hypothesis that carries a measured transform: it says where the node "
        "is, so only odometric drift may separate that from the node's place code; ~2 sigma of Bicocca's "
        "loop-transform noise, measured in docs/BENCHMARKS.md [ours]",
    )
    loop_radius_per_m: float = Field(
        0.05,
        ge=0,
        description="gate growth per metre travelled between the two nodes: odometric drift allowance [ours]",
    )
    loop_outer_gate: float | None = Field(
        0.7,
        gt=0,
        le=1,
        description="a visual hypothesis that puts its node at or beyond this fraction of the gate's limit from the "
        "node's map pose waits for a consistent group as one outside the gate does (map.outside_min_support); None = "
        "every hypothesis inside the gate becomes a link at once. 0.7 chosen among 0.35 / 0.5 / 0.6 / 0.7 on the "
        "simulated tuning runs and the runs at 0.8 and 1.2 m/s: accepted false closures 77 -> 48 at the same maps "
        "[ours, docs/MODEL.md item 97]",
    )
    loop_oblique_turn_rad: float | None = Field(
        0.45,
        gt=0,
        description="a visual hypothesis whose recognition read a turn of at least this from its key frame's view "
        "(the image shift's heading, LoopHypothesis.meta['view_turn']) waits for a consistent group as one outside "
        "the gate does (map.outside_min_support): across a wide turn the two views share only part of the scene, and "
        "the robot may stand well beside the key frame's line of view, which the shift cannot tell from a turn. "
        "None = such a hypothesis is gated as any other. 0.45 chosen among 0.35 / 0.45 / 0.55 on the 64 simulated "
        "choosing runs: maps summed 22.203 -> 22.121 m, revisits 260 -> 262, accepted false closures 2 -> 2 (0.35: "
        "22.037 m but 260 revisits and 3 false) [ours, docs/MODEL.md item 124]",
    )
    loop_retract_below: float | None = Field(
        0.03,
        gt=0,
        le=1,
        description="an accepted loop link still unverified when its support window ends is judged "
        "map.loop_retract_after_m later: weighted below this by the robust kernel then, it is retracted (held at the "
        "kernel's floor weight for good, its decision rejected); None = every such link stays at the kernel's weight. "
        "0.03 chosen among 0.01 / 0.03 / 0.1 on the simulated tuning runs and the runs at 0.8 and 1.2 m/s: accepted "
        "false closures 48 -> 12 at better maps [ours, docs/MODEL.md item 99]",
    )
    loop_retract_after_m: float = Field(
        0.0,
        ge=0,
        description="metres of path after its support window (map.loop_support_window_m) at which an unverified "
        "link is judged for retraction (map.loop_retract_below), once a closure verified since it was made has had "
        "the chance to move the map. 0 (judged when its window ends) chosen among 0 / 5 / 20 on the simulated "
        "tuning runs and the runs at 0.8 and 1.2 m/s: accepted false closures 6 -> 3, maps 22.646 -> 22.625 m "
        "summed; faded links made 5-25 m before a run's end are no longer left unjudged [ours, docs/MODEL.md "
        "items 99, 121]",
    )
    loop_retract_groups: bool = Field(
        True,
        description="the links a group of recognitions outside the gate (or in its outer part) made are judged for "
        "retraction like unverified ones (map.loop_retract_below, map.loop_retract_after_m, counted from the group's "
        "acceptance). On by default: on the simulated tuning runs and the runs at 0.8 and 1.2 m/s accepted false "
        "closures 12 -> 9 at maps 22.124 -> 22.156 m summed, revisits unchanged [ours, docs/MODEL.md item 100]",
    )
    loop_heading_radius_rad: float | None = Field(
        0.8,
        gt=0,
        description="heading part of the gate for a visual hypothesis: the heading it gives the named node may differ "
        "from the node's map heading by this much plus loop_heading_per_m per metre of the drift path, or the "
        "hypothesis is outside the gate (it waits for a consistent group, map.outside_searches); None = no heading "
        "gate. Measured transforms keep their own heading check (loop_transform_consistency_rad) [ours]",
    )
    loop_heading_per_m: float = Field(
        0.02,
        ge=0,
        description="growth of the gate's heading part per metre of the drift path (loop_drift) [ours]",
    )
    loop_heading_anchored_rad: float | None = Field(
        0.4,
        gt=0,
        description="once a verified closure has anchored the map (and the odometry's heading bias with it, "
        "odometry_bias_sigma), the gate's heading part is at most this plus loop_heading_anchored_sd of the "
        "odometry's own heading standard deviation over the drift path (odometry_information_per_m): what is left "
        "of the heading drift is the odometry's random walk, not the bias that turned true closures by up to 2 rad "
        "before the first one. None = the unanchored part throughout [ours, docs/MODEL.md item 107]",
    )
    loop_heading_anchored_sd: float = Field(
        1.0,
        ge=0,
        description="standard deviations of the odometry's heading random walk over the drift path that the "
        "anchored heading part (loop_heading_anchored_rad) adds to its base [ours, docs/MODEL.md item 107]",
    )
    loop_heading_group_sd: float | None = Field(
        3.0,
        ge=0,
        description="once a verified closure has anchored the map, a visual hypothesis outside the gate may wait for "
        "a consistent group only if the heading it gives its node is within loop_heading_anchored_rad plus this many "
        "standard deviations of the odometry's heading walk over the drift path; beyond, it is rejected at once. "
        "None = every such hypothesis waits [ours, docs/MODEL.md item 111]",
    )
    loop_turned_group: int | None = Field(
        6,
        ge=2,
        description="a visual hypothesis turned beyond loop_heading_group_sd is not rejected at once: it waits for a "
        "long group, at least this many mutually consistent recognitions (outside_min_support's test) spread over at "
        "least loop_turned_group_m of the robot's path; a gyro bias that wanders turns the map by 2 rad over a long "
        "excursion, and the right recognitions at its end were all rejected, where the false groups that item 111 "
        "refuses were 3 recognitions within 1.1 m of path. None = rejected at once (item 111) [ours, docs/MODEL.md "
        "item 130]",
    )
    loop_turned_group_m: float = Field(
        3.0,
        ge=0,
        description="metres of the robot's path a long group (loop_turned_group) must spread over [ours, "
        "docs/MODEL.md item 130]",
    )
    loop_radius_bias_sd: float = Field(
        2.0,
        ge=0,
        description="gate growth for the error of the odometry's estimated heading bias (odometry_bias_sigma): a "
        "rate error e turns the robot's heading by e t over the t seconds since the last verified closure anchored "
        "it, and moves its map pose by e D^2 / (2 v) over those D metres at speed v; the gate adds this for e = "
        "this many posterior standard deviations of the estimate kept by the last whole solve (0 while none is "
        "kept). 0 = off. 2 chosen on the Bicocca world's 16 simulated tuning seeds (docs/MODEL.md item 58) [ours]",
    )
    loop_bias_per_node: bool = Field(
        True,
        description="loop_radius_bias_sd's allowance counted per node: a node d metres back gets e d (D - d/2) / v, "
        "the heading error over the path between it and the robot only, instead of e D^2 / (2 v) for every node "
        "(False). Chosen on the 60 simulated choosing runs (docs/MODEL.md items 102 and 104) [ours]",
    )
    loop_bias_unkept: bool = Field(
        True,
        description="loop_radius_bias_sd's allowance also for an estimate a whole solve made and did not keep "
        "(odometry_bias_significance, odometry_bias_observed): the map then applies no bias, so the odometry's may be "
        "the estimate's size plus loop_radius_bias_sd of its posterior standard deviations, e = |b| + k sd. False = no "
        "allowance while no estimate is kept (the model before: with a gyro drifting -0.0006 rad/s, too little to "
        "keep, five of six simulated Bicocca-world maps of the choosing seeds were 8.9-11.7 m off; with "
        "loop_heading_bias, 44 choosing runs at other biases 78.4 -> 36.0 m summed) [ours, docs/MODEL.md item 125]",
    )
    loop_bias_walk: float = Field(
        0.0,
        ge=0,
        description="(rad/s)/sqrt(s): how fast the odometry's heading bias may wander (a gyro's rate random walk; "
        "temperature and bias instability move it over a run). The whole solves estimate one rate for the run; after T "
        "seconds the bias may stand off that average by walk sqrt(T / 3), which loop_radius_bias_sd's allowance adds "
        "to the estimate's standard deviation in quadrature. 0 (default) = a constant bias. An option for a gyro known "
        "to wander, set to its data sheet's rate random walk: with the bias wandering 1e-4 (rad/s)/sqrt(s), 1e-4 took "
        "held-out Bicocca-world maps from 36.0 to 16.4 m summed (seeds 297-299); with a constant bias it grows the "
        "gate over whole maps (the 64 simulated choosing runs 22.18 -> 42.72 m) [ours, docs/MODEL.md item 126]",
    )
    loop_heading_bias: bool = Field(
        True,
        description="the gate's anchored heading part (loop_heading_anchored_rad, loop_heading_group_sd) adds the "
        "turn that loop_radius_bias_sd's rate error e (with loop_bias_unkept, the unkept estimate's size too) makes "
        "over the seconds since the last verified closure, e t: what is left of the heading drift once a closure has "
        "anchored the map is the odometry's walk and that error, not the walk alone. False = the walk alone (the model "
        "before) [ours, docs/MODEL.md item 125]",
    )
    loop_drift: Literal["verified", "graph"] = Field(
        "graph",
        description="the path over which drift may separate a visual hypothesis's node from the robot, for the gate: "
        "the shortest path to the node through the map's odometric and used loop links ('graph', default: a "
        "closure shortens it only towards the places it joins), or the path since the node was made or since the "
        "last verified closure, whichever is shorter ('verified'). On 16 seeds of the simulated Bicocca world "
        "'graph' took the median map ATE from 6.3 to 2.1 m (docs/MODEL.md item 47) [ours]",
    )
    exclude_recent: int = Field(
        5, ge=0, description="N_excl, recent nodes excluded from loop closure and pruning [spec §5]"
    )
    initial_pose: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="first node (0,0,0) [S §2.4]")
    alpha: float = Field(0.5, gt=0, le=1, description="relaxation correction constant alpha, Eq. 14 [S], [ORS]")
    relax_loops: int = Field(10, ge=0, description="EXP_LOOPS, relaxation sweeps per action [ORS]")
    prune_block_m: float = Field(0.5, gt=0, description="b, pruning block side, Eq. 15 [spec §4]")
    prune_online: bool | None = Field(
        None,
        description="merge a new node into an older node of its block, Eq. 15 / Fig. 7 [S]. None (default): "
        "only in runs of measured loop proposals (hippomap run-odometry), not in camera runs, whose revisits then "
        "keep their own nodes tied to the old ones by loop links: a merge copies the map's relative pose of the two "
        "nodes into a link as stiff as odometry and fixes the robot's offset from the old node, and in camera runs "
        "(visual links 0.2 m off) that cost 30-40 % of the map ATE, while on Bicocca's measured closures merging "
        "gained 0.6-2.5 % [ours, docs/MODEL.md item 40]",
    )
    prune_graph_radius_m: float | None = Field(
        3.0,
        gt=0,
        description="online pruning only merges into nodes within this path length of the current node along the "
        "graph: literal Eq. 15 merging (None) is an unverified loop closure in a drifted map; 3 m measured best on "
        "Bicocca and the synthetic loop (docs/BENCHMARKS.md) [ours]",
    )
    loop_relocalise: bool = Field(
        False,
        description="on a verified loop closure the matched node becomes the current node ([ORS] "
        "on_set_experience); False (default) keeps the current node and only adds the loop links, so a revisit "
        "adds its own nodes, tied to the old ones by loop links: measured better on the simulated tuning set and "
        "on all three Bicocca files, at the cost of more nodes per revisit (docs/MODEL.md item 35) [ours]",
    )
    loop_min_support: int = Field(
        3,
        ge=1,
        description="mutually consistent hypotheses needed before a loop closes (geometric check); 3 is the "
        "smallest that accepted no false proposal of B25b_0.000 (docs/BENCHMARKS.md) [ours]",
    )
    loop_support_window_m: float = Field(
        5.0,
        gt=0,
        description="metres of path a hypothesis waits for support, and an accepted one backs newer ones; "
        "in metres, not steps or frames, so that it means the same at any speed, frame rate and key-frame spacing "
        "(B25b: the former 50 steps of 0.09 m) [ours]",
    )
    outside_min_support: int = Field(
        3,
        ge=0,
        description="mutually consistent visual hypotheses (map.outside_searches says whose) needed before a group "
        "that names nodes outside the gate becomes loop links (0: such hypotheses are rejected like any other outside "
        "the gate); "
        "docs/MODEL.md [ours]",
    )
    outside_searches: Literal["global", "all"] = Field(
        "all",
        description="which visual hypotheses that fall outside the gate wait for a consistent group "
        "(map.outside_min_support) instead of being rejected: 'global', only a global search's; 'all', a gated "
        "search's too (its key frame was inside the gate, the recognition's offset put it outside); "
        "docs/MODEL.md [ours]",
    )
    outside_window_m: float = Field(
        15.0,
        gt=0,
        description="metres of path an outside-the-gate hypothesis waits for consistent support "
        "(global searches run every mapper.global_search_every_m, and recognise a true revisit about one time in "
        "three on the simulated worlds) [ours]",
    )
    loop_gate: Literal["map", "place_code"] = Field(
        "map",
        description="what the gate compares: the robot's map pose with the node's ('map': the map learns from "
        "loop closures, the place code does not) or the two place codes (Eq. 13 [S]); docs/MODEL.md [ours]",
    )
    loop_view_rad: float = Field(
        0.4,
        gt=0,
        description="a verified group's fit may turn the robot at most this far from the heading of the "
        "key frames it recognised (a recognised view is seen from roughly the same direction; half of a 60-70 "
        "degree field of view) [ours]",
    )
    loop_fit_window_m: float | None = Field(
        2.5,
        gt=0,
        description="metres of path over which accepted visual hypotheses back a group's relative-pose fit: one "
        "rigid transform of the dead-reckoned path cannot follow the odometry's heading drift over a longer stretch; "
        "None = the whole loop_support_window_m. 2.5 chosen among 1.5 / 2 / 2.5 / 3.5 / None on the simulated "
        "tuning runs [ours, docs/MODEL.md]",
    )
    loop_fit_min_spread_m: float = Field(
        0.5,
        gt=0,
        description="a group of visual hypotheses whose robot positions spread over at least this fits "
        "its rotation from the positions, else from the headings (relative-pose fit, hippomap.loop_closure) [ours]",
    )
    loop_consistency_m: float = Field(
        0.5,
        gt=0,
        description="max translation error of a loop cycle [ours: measured on Bicocca, 1.0 let false loops in]",
    )
    loop_consistency_rad: float = Field(
        0.1, gt=0, description="max rotation error of a loop cycle [ours: as above, was 0.3]"
    )
    loop_transform_consistency_rad: float = Field(
        0.02,
        gt=0,
        description="max rotation error of a loop cycle between two hypotheses that both carry a measured "
        "transform: such a cycle is made of two measurements and a short stretch of odometry, so it must close as "
        "tightly as the measurements do (B25b loop information 600-3800 rad^-2, i.e. sigma 0.016-0.04 rad). 0.1 let "
        "true closures biased by 0.12 rad bend the Bicocca map below odometry's accuracy (docs/BENCHMARKS.md) [ours]",
    )
    loop_consistency_rad_per_m: float = Field(
        0.005,
        ge=0,
        description="heading drift allowed per metre of odometry inside such a cycle (robot path between "
        "the two proposals plus map path between the two nodes), added to loop_transform_consistency_rad [ours]",
    )
    relax_tolerance_m: float = Field(
        1e-4,
        gt=0,
        description="relaxation runs relax_loops sweeps per step until a sweep moves no node more than "
        "this; then it stops until the graph changes (no work between closures) [ours]",
    )
    loop_kernel: Literal["cauchy", "dcs", "none"] = Field(
        "cauchy",
        description="robust kernel that sets each loop link's weight from its residual on the converged "
        "map (iteratively reweighted relaxation); 'none' keeps every accepted link at weight 1 [ours]",
    )
    loop_kernel_width: float = Field(
        1.0,
        gt=0,
        description="kernel width of a measured loop link, in standard deviations of its information: a "
        "link whose residual is this many sigmas keeps half its weight (Cauchy) [ours: Bicocca proposals]",
    )
    visual_kernel_width: float = Field(
        3.0,
        gt=0,
        description="kernel width of a visual loop link: its relative pose is fitted from recognitions, "
        "not measured, so its errors reach about three times a measured link's (docs/MODEL.md) [ours]",
    )
    loop_accept: Literal["robust", "verified"] = Field(
        "robust",
        description="'robust': every hypothesis that passes the gate becomes a loop link weighted by the "
        "robust kernel, and cycle consistency only decides which are verified (fitted, relocalising); 'verified': "
        "only verified hypotheses become links, the rest are rejected [ours, docs/MODEL.md]",
    )
    loop_weight_init: Literal["one", "kernel"] = Field(
        "kernel",
        description="weight of a new loop link: 1 (applied fully, then revised on the converged map) or the "
        "kernel weight of its residual on the map as it stands [ours]",
    )
    trust_verified: bool = Field(
        False,
        description="verified loop links (cycle consistency) keep weight 1; the kernel weighs only unverified "
        "ones. False (default): the kernel revises every loop link; measured better on Bicocca and the simulated "
        "worlds (biased true closures fade too) [ours, docs/MODEL.md]",
    )
    reweight_tolerance: float = Field(
        0.05,
        gt=0,
        lt=1,
        description="a weight change above this relaxes again; so does a weight falling tenfold, however small "
        "the change (a faded link's stale weight would go on bending the map, docs/MODEL.md item 52) [ours]",
    )
    solver: Literal["relax", "jacobi", "lsq"] = Field(
        "lsq",
        description="map correction after each action: 'relax' = [ORS] per-link relaxation (Eq. 14), vectorised by "
        "edge colour; 'jacobi' = simultaneous Eq. 14 with degree-normalised alpha; 'lsq' = Gauss-Newton SE(2) pose "
        "graph, exact, the default: relaxation needs O(N^2) sweeps to spread a closure around an N-node loop "
        "(docs/MODEL.md) [ours]",
    )
    lsq_iterations: int = Field(
        10, ge=1, description="max Gauss-Newton iterations per correction when solver='lsq' [ours]"
    )
    lsq_rotation_init: bool = Field(
        True,
        description="before a whole-map lsq solve, re-initialise the poses headings first, then positions "
        "(two linear solves, LAGO's idea): from the odometric poses Gauss-Newton can settle with a long loop's "
        "heading error spread wrongly, leaving true closing links a metre off for the kernel to fade "
        "[ours, docs/MODEL.md]",
    )
    lsq_branch_solve_iterations: int | None = Field(
        10,
        ge=1,
        description="when a turned branch of the headings-first re-initialisation starts below the wrapped reading, "
        "it and the wrapped reading are judged after this many Gauss-Newton steps of the whole solve (on copies) "
        "instead of at their inits, whose costs favoured a wrong whole turn of a fast-drifting gyro; None = judged "
        "at the inits [ours, docs/MODEL.md item 112]",
    )
    lsq_window_hops: int = Field(
        40,
        ge=0,
        description="when every link changed since the last solve agrees with the map within "
        "lsq_window_residual_m, solve only the nodes within this many links of them (10 m at the default node "
        "spacing), holding the nodes around; 0 = always the whole map. Keeps the cost of re-localising along a "
        "mapped path independent of the map's size [ours, docs/MODEL.md]",
    )
    lsq_window_max_nodes: int | None = Field(
        250,
        ge=1,
        description="... and no more nodes than this: the window takes the most hops (up to lsq_window_hops) "
        "whose nodes number at most this, so that on a path retraced lap after lap, where the window reaches "
        "every pass through the loop links, a step's cost stops growing with the laps; None = hops only. 250: "
        "the smallest of 100 / 150 / 200 / 250 that left every Bicocca-world tuning map as it was "
        "[ours, docs/MODEL.md item 29]",
    )
    lsq_defer_m: float = Field(
        1.0,
        ge=0,
        description="a correction whose changed links all agree with the map within lsq_window_residual_m waits "
        "until the robot has gone this far (m of path) since the last solve, or lsq_defer_s has passed, and is "
        "then solved with the ones after it; a change that disagrees is solved at once; 0 = solve every change at "
        "once [ours, docs/MODEL.md]",
    )
    lsq_defer_s: float = Field(
        5.0,
        gt=0,
        description="... and no longer than this many seconds since the last solve: a robot that stops or turns "
        "on the spot still gets its map settled [ours, docs/MODEL.md]",
    )
    lsq_window_every: int = Field(
        10,
        ge=1,
        description="after this many local solves the next correction solves the whole map (and revises "
        "the robust weights, which only a whole solve does) [ours]",
    )
    lsq_whole_every_map: float | None = Field(
        1.0,
        gt=0,
        description="... and not before the local solves since the last whole solve have moved, summed, this many "
        "times the map's nodes: a whole solve costs about as much per node as a local one, so at 1 the whole "
        "solves cost at most about what the local solves between them do, and a step's cost stops growing with "
        "the map's size; None = every lsq_window_every local solves, whatever the map's size "
        "[ours, docs/MODEL.md item 108]",
    )
    lsq_whole_every_work: float | None = Field(
        0.1,
        gt=0,
        description="... and not before the local solves since the last whole solve have done, summed, this many "
        "times its work (the nonzeros of its factors): on a path retraced lap after lap a whole solve's factor grows "
        "faster than the map's nodes, so the node rule let the whole solves' share of a step grow with the laps; "
        "with this rule it is bounded by a multiple of the local solves'. None = the node rule alone. 0.1: the "
        "larger of 0.1 and 0.2 that left every choosing map within 1.3 mm [ours, docs/MODEL.md item 117]",
    )
    lsq_window_residual_m: float = Field(
        0.5,
        gt=0,
        description="largest residual of a changed link that still counts as a local correction: solved in a window, "
        "deferred by lsq_defer_m, and when solved whole, without the headings-first init; a larger one is a new loop, "
        "solved whole at once (but see lsq_window_anchored_residual_m). 0.75 everywhere was measured and not kept: "
        "a first closure after 6 rad of gyro drift that agreed within 0.67 m by coincidence was then solved as a "
        "re-localisation and the drift never unwound [ours, docs/MODEL.md items 29 and 118]",
    )
    lsq_window_anchored_residual_m: float | None = Field(
        0.75,
        gt=0,
        description="... and up to this residual when the links beyond that bar are visual (their disagreement "
        "mostly their own depth misread; a measured transform's is the map's) and the map round the robot is "
        "anchored: a used loop link that the change does not touch lies within lsq_window_hops links of the "
        "robot's end of a changed link, so the change is a re-localisation on a closed map, not a new loop. 0.75: "
        "the bar item 118 measured everywhere, where its saving was (0.94 x per frame on a 30-lap loop); None = "
        "lsq_window_residual_m everywhere [ours, docs/MODEL.md item 119]",
    )
    lsq_window_iterations: int | None = Field(
        1,
        ge=1,
        description="Gauss-Newton iterations of a local solve (a re-localisation whose changed links all agree "
        "with the map within lsq_window_residual_m): the problem is nearly linear at the current poses, so one "
        "linear solve is its solution to a few mm, as iSAM2 applies one linear update per step and relinearises "
        "later; the next local solve and the whole solves take up what is left. None = lsq_iterations "
        "[ours, docs/MODEL.md item 64]",
    )
    lsq_window_max_fraction: float = Field(
        0.9,
        gt=0,
        le=1,
        description="a local window holding more than this fraction of the map's nodes is solved as the whole "
        "map instead. 0.5 before: on maps of a few hundred nodes (a loop or corridor world) a 40-hop window is "
        "about half the map, so most re-localisation solves were whole ones and their cost grew with the map "
        "[ours, docs/MODEL.md item 50]",
    )
    lsq_step_tolerance: float = Field(
        1e-4,
        gt=0,
        description="the map's Gauss-Newton solves stop once the largest update of any unknown is below this "
        "(m or rad): a tenth of a millimetre is far below what the map can tell apart, and the solves of "
        "small changes no longer spend a last linear solve confirming a micrometre step (1e-6 before) "
        "[ours, docs/MODEL.md item 50]",
    )
    lsq_weighted: bool = Field(
        True,
        description="solver='lsq' weights each link by its information (below) instead of alike: odometric "
        "links by their length, loop links by loop_information [ours]",
    )
    odometry_information_per_m: tuple[_Positive, _Positive] = Field(
        (362.0, 3620.0),
        description="information of 1 m of odometry, (x/y in m^-2, heading in rad^-2); a link of "
        "length d gets this / d (variance grows with the path). Default: the B25b g2o files' 4000 / 40000 per 0.0905 m "
        "step [ours, from the data]",
    )
    odometry_bias_sigma: float = Field(
        0.02,
        ge=0,
        le=1,
        description="lsq: estimate a constant heading bias of the odometry (rad/s: a gyro's drift, "
        "a wheel-radius mismatch while driving) with the poses in every whole solve, with a zero-mean prior of this "
        "standard deviation (about an uncalibrated MEMS gyro's turn-on bias); each odometric link's heading change "
        "is corrected by bias x its duration, and only a significant estimate is kept "
        "(odometry_bias_significance) and observed by the loops (odometry_bias_observed). 0 = no bias "
        "(odometry calibration as in Kuemmerle et al. 2011) [ours, docs/MODEL.md item 34]",
    )
    odometry_bias_significance: float = Field(
        3.0,
        ge=0,
        description="with odometry_bias_sigma > 0: a whole solve keeps its bias estimate only when "
        "|bias| exceeds this many of its posterior standard deviations (Wald test); otherwise the map is solved "
        "without a bias, as with the option off. The posterior counts only the loop links whose heading the "
        "solution explains (docs/MODEL.md item 52). 0 = always keep it [ours, docs/MODEL.md]",
    )
    odometry_bias_observed: float | None = Field(
        0.25,
        gt=0,
        le=1,
        description="with odometry_bias_sigma > 0: a whole solve keeps its bias estimate only when the loops observe "
        "it, i.e. its posterior standard deviation is at most this fraction of the prior's (the closures, not the "
        "prior, carry the estimate); null = no such test. 0.25: tuning maps identical for 0.1-0.5; set after a "
        "held-out corridor run whose first closure gave a wrong bias at 4 sigma but only 0.55 x the prior's sigma "
        "[ours, docs/MODEL.md item 34]",
    )
    odometry_turn_variance: float = Field(
        0.0,
        ge=0,
        description="heading variance (rad^2) an odometric link gains per radian it turns, on top of its "
        "length's: a gyro or wheel-odometry heading error grows with the turning too, so that a corner is not "
        "held stiffer than a straight [ours, docs/MODEL.md]",
    )
    visual_loop_information: tuple[_Positive, _Positive] = Field(
        (100.0, 1000.0),
        description="information of a visual loop link (x/y, heading), as for a measured one: "
        "softer visual links left loops partly open on the simulated worlds (docs/MODEL.md) [ours]",
    )
    visual_lateral_information: float | None = Field(
        10.0,
        gt=0,
        description="information (m^-2) of a visual loop link beside the robot's heading (y in the "
        "link's source frame), apart from visual_loop_information's x/y along it: a recognition places the robot at "
        "the matched key frame, moved along its view by looming, but cannot see how far beside it the robot stands, "
        "so odometry decides there; None = as x/y. 10 chosen among 3 / 10 / 30 / None on the simulated tuning runs "
        "[ours, docs/MODEL.md item 41]",
    )
    visual_solve_loosening: float = Field(
        3.0,
        ge=1,
        description="a visual loop link's x and y information in the solve is divided by this; the robust kernel "
        "still judges the link at the undivided x (as looming's along_sigma, item 84): the several links one "
        "revisit makes share one error (one offset beside the path, one depth misread), so at full information "
        "together they outweighed the odometry beside them. 3 chosen among 1 / 2 / 3 / 5 / 8 on the simulated "
        "tuning runs [ours, docs/MODEL.md item 88]",
    )
    loop_information: tuple[_Positive, _Positive] = Field(
        (100.0, 1000.0),
        description="information of a loop link (x/y, heading): the middle of the B25b g2o loop "
        "edges' 60-380 / 600-3800 [ours, from the data]",
    )


class MapperConfig(_Frozen):
    """Glue between the pathways (paper Fig. 1)."""

    keyframe_interval: int | None = Field(
        None,
        ge=1,
        description="learn a key frame every so many raw frames ([S] §3.2: 100) instead of by distance "
        "and turn; None = by distance and turn, which means the same at any frame rate and speed [ours]",
    )
    keyframe_distance_m: float = Field(
        0.5,
        gt=0,
        description="learn a key frame after this many metres of odometric path [ours: chosen on simulated "
        "worlds, docs/MODEL.md]",
    )
    keyframe_seconds: float | None = Field(
        0.75,
        gt=0,
        description="... and no sooner than this many seconds after the last key frame, off a familiar path (key "
        "frames made by turning are not held back): a robot faster than keyframe_distance_m / keyframe_seconds "
        "(0.67 m/s) learns and recognises as often per second as one at that speed, not per metre. 0.75 s binds "
        "at the speed where keyframe_familiar_seconds does; chosen among 0.6 / 0.75 / 1.0 s on simulated runs at "
        "0.8 and 1.2 m/s (1.0 s would bind at the Bicocca world's recorded speeds). None = by distance only [ours, "
        "docs/MODEL.md item 95]",
    )
    keyframe_familiar_distance_m: float | None = Field(
        1.0,
        gt=0,
        description="on a familiar path (the last key frame's recognition verified a loop), the next key frame "
        "comes after this many metres instead of keyframe_distance_m: fewer recognitions while the robot "
        "retraces its map (novelty-driven key frames). None = keyframe_distance_m always. 1.0 chosen among "
        "None / 1.0 / 1.5 / 2.0 on the simulated tuning runs (loops, corridors and the Bicocca world's 16 seeds: "
        "lower map ATE on both, a third fewer recognitions on the loops); docs/MODEL.md item 44 [ours]",
    )
    keyframe_familiar_seconds: float | None = Field(
        1.5,
        gt=0,
        description="... and no sooner than this many seconds after the last key frame: a robot that retraces its "
        "map fast recognises as often per second as one at 0.67 m/s, not per metre, so its cost per frame grows "
        "less with its speed. 1.5 s binds only above 0.67 m/s, faster than any run the familiar spacing was chosen "
        "on (2 s changed the Bicocca world's maps); None = by distance only [ours, docs/MODEL.md item 92]",
    )
    keyframe_familiar_after_m: float = Field(
        0.0,
        ge=0,
        description="... but only once the key frames have verified loops over at least this much path in a row "
        "(a long retraced stretch, not a brief revisit) [ours, docs/MODEL.md item 44]",
    )
    recognition_view_rad: float | None = Field(
        2 * math.pi / 3,
        gt=0,
        description="a key frame is a recognition candidate only if its heading on the map is within this of the "
        "robot's (plus recognition_view_rad_per_m of drift): a camera turned further away sees none of what it saw. "
        "2 pi / 3 keeps every recognition the simulated tuning runs accepted (map headings up to 1.7 rad apart, the "
        "map's own heading error included); None = every gated key frame [ours, docs/MODEL.md item 45]",
    )
    recognition_view_rad_per_m: float = Field(
        0.05,
        ge=0,
        description="... plus this per metre of drift path (since the last verified closure or the key frame, "
        "whichever is shorter): the map's headings drift as its positions do (loop_radius_per_m) [ours]",
    )
    recognition_view_fovs: float | None = Field(
        None,
        gt=0,
        description="where the camera's field of view is known (camera_hfov_deg), recognition_view_rad is at most "
        "this many fields of view (the drift allowance still added): two views turned further apart than the camera "
        "sees share almost nothing; None = recognition_view_rad whatever the camera. Off by default: 1 left the "
        "simulated tuning maps as they were with 0.94 x the fixations, but the mapper's CPU per frame fell by a few "
        "per cent at most and a few more false closures were accepted (none used) [ours, docs/MODEL.md item 94]",
    )
    keyframe_turn_rad: float = Field(
        0.35, gt=0, description="... or after turning this much (a robot turning on the spot sees new views) [ours]"
    )
    recognition_min_path_m: float = Field(
        5.0,
        ge=0,
        description="a key frame can be recognised only after the robot has travelled this far since "
        "learning it: the camera still sees the scene it took a few metres back (such matches are not loop "
        "closures); chosen on the simulated tuning worlds, docs/MODEL.md [ours]",
    )
    recognition_every_s: float | None = Field(
        None,
        gt=0,
        description="a key frame is recognised only if this many seconds have passed since the last key frame that "
        "was; the others are learned without a recognition. None = every key frame (measured, not kept: fewer revisits "
        "and a growing memory) [ours, docs/MODEL.md item 93]",
    )
    sequence_window_m: float | None = Field(
        None,
        gt=0,
        description="after a key frame's recognition that the map did not reject, search the next key frame first "
        "among the candidates learned within this many metres of path of the frame it named (a robot retracing its "
        "path meets the old path's key frames in their order), then among the rest (or all at once with those "
        "primed: sequence_prior). Measured, not kept: 5 m (the "
        "best of 2 / 3 / 5 / 8 m on the 64 simulated choosing runs, maps summed 22.667 -> 22.573 m) closes more "
        "of the Bicocca world's long returns but on held-out seeds 234-236 left the maps summed 4.6 % worse, the "
        "grids and halls worse and one false closure used: a search among few key frames accepts a neighbour the "
        "wider competition would have refused. None = every candidate at once (docs/MODEL.md item 114) [ours]",
    )
    sequence_prior: float | None = Field(
        None,
        ge=0,
        description="with sequence_window_m: the old path's sequence is not searched first but primed, every "
        "candidate searched at once with those of the sequence starting each attempt at this activity instead of 0 "
        "(below visual.decision_threshold, 0.9): what the robot expects next needs less evidence, but still "
        "competes with every candidate and is verified. Measured, not kept: 0.2 (the best of 0.1 / 0.2 / 0.3 / "
        "0.4 at 5 m on the 64 simulated choosing runs, maps summed 22.667 -> 22.445 m, 0.91 x the fixations) left "
        "held-out seeds 238-240 summed 8.853 -> 9.045 m with 0.90 x the fixations: a primed neighbour wins before "
        "the nearest key frame and the links lie further off along the path; holding those links loosely along "
        "the path did not mend it (item 116). None = the sequence searched first, then the rest (docs/MODEL.md items "
        "114 and 115) [ours]",
    )
    global_search_after_m: float | None = Field(
        40.0,
        ge=0,
        description="after this much odometric path without a verified loop closure, a key frame that "
        "the gated search did not recognise is also searched against every recognisable key frame outside the "
        "gate (its hypotheses need a consistent group: map.outside_min_support); None: never. 40 m chosen among "
        "20 / 30 / 40 / 60 / 90 m on the Bicocca world's 16 simulated tuning seeds (60 m before, chosen on two "
        "of them; docs/MODEL.md item 38) [ours]",
    )
    global_search_every_m: float = Field(
        2.0,
        gt=0,
        description="metres of path between two global searches (each costs a recognition against the "
        "whole visual memory). 2 m chosen among 1 / 2 / 3 / 5 / 8 m and none on the simulated tuning runs with "
        "every other default: the best maps (the Bicocca world's 16 tuning seeds sum 19.28 -> 18.84 m, every "
        "revisit closed, no false closure used; 5 m, 8 m and none lost a revisit) at 0.85 x the recognitions; "
        "corridors with three times the gyro bias close their return only with searches (docs/MODEL.md item 38) [ours]",
    )
    global_search_give_up_evidence: float | None = Field(
        0.9,
        gt=0,
        le=1,
        description="the give-up bar (visual.give_up_evidence) of a global search: against the whole visual memory "
        "some frame's activity passes the gated search's 0.5 by chance in most attempts, so a search that finds "
        "nothing ran every attempt. 0.9, the decision threshold: on the 24 simulated tuning runs every global "
        "search that named a true place had reached it within its first attempts; 23 of the 24 maps stayed the same "
        "to the last digit, with 3-14 % fewer fixations (docs/MODEL.md item 69). None = visual.give_up_evidence [ours]",
    )
    learn_recognised: bool = Field(
        False,
        description="also learn a key frame that was recognised: False learns only novel views (as "
        "[ORS]'s view templates), so a key frame is always anchored to the node of the pass that first saw it, "
        "and the visual memory grows with the places visited, not with the time spent there [ours, docs/MODEL.md]",
    )
    camera_hfov_deg: float | None = Field(
        None,
        gt=0,
        lt=180,
        description="horizontal field of view of the camera; when known, the image shift of a "
        "recognition's saccade correspondences turns into the robot's heading relative to the matched key frame "
        "[ours]",
    )
    view_distance_m: float | None = Field(
        4.5,
        gt=0,
        description="typical distance from the camera to the scene it sees; the scale change of a "
        "recognition's saccade correspondences (looming) times this is how far the robot stands ahead of or behind "
        "the matched key frame along its view, so a visual loop link is not off by up to a key-frame spacing along "
        "the track, and its image shift measures heading + lateral offset / this (shift_coupling). None = the robot "
        "is taken to be at the key frame. 4.5 chosen among 3 / 3.75 / 4.5 / 6 on the 24 simulated tuning runs (3 "
        "before, chosen for looming alone; docs/MODEL.md items 37 and 72) [ours]",
    )
    looming_on_sphere: bool = Field(
        True,
        description="where the camera's field of view is known (camera_hfov_deg), a recognition's looming is "
        "measured between the correspondences' directions on the viewing sphere (azimuth and elevation), where a "
        "turn of the camera moves every point alike, instead of between their image positions, where the same "
        "turn changes the spacing of points as they move towards the image centre and reads as a step along "
        "the view. Not tuned: geometry; False = image positions (before; docs/MODEL.md item 122) [ours]",
    )
    looming_spread: float | None = Field(
        0.5,
        ge=0,
        description="how far a scene's depth strays from view_distance_m, as a fraction of it: a recognition's "
        "looming offset d along the key frame's view is then uncertain by this x |d| (LoopHypothesis.along_sigma), "
        "and its loop link that much looser along the robot's heading in the solve, so that a deep or shallow view "
        "read through view_distance_m bends the map's lengths less; the robust kernel still weighs the link at its "
        "own information. 0.5: the spread of the simulated views' depths (docs/MODEL.md items 73 and 84), not "
        "tuned; None or 0 = the link's information alone [ours]",
    )
    reanchor_span: int | None = Field(
        15,
        ge=1,
        description="a recognition's loop link names the node, among this many either side of the matched key "
        "frame's node along the old path, nearest the place the recognition claims (the key frame's pose moved by "
        "the looming and the image shift), instead of the key frame's node: the link then joins nodes that stood "
        "at the same place. None = the key frame's node [ours, docs/MODEL.md item 103]",
    )
    shift_coupling: bool = Field(
        True,
        description="a recognition's image shift measures its heading plus its offset beside the key frame "
        "over view_distance_m, and its loop link holds that combination (a turn and a sideways step shift the "
        "scene alike), so that the map, not the shift, decides how much of it is turn; False = the shift is "
        "the heading alone. Needs camera_hfov_deg [ours, docs/MODEL.md item 56]",
    )
    mode: Literal["map", "localise"] = Field(
        "map",
        description="'map': build the map (new nodes, key frames, loop links); 'localise': recognise places "
        "and relocalise the robot through the same loop-closure path, but add no node, link or key frame and never "
        "move the map (localisation in a saved map, as RTAB-Map's localisation mode) [ours, docs/MODEL.md]",
    )

    @property
    def looming_hfov_deg(self) -> float | None:
        """The field of view a recognition's looming is read with: ``camera_hfov_deg`` when ``looming_on_sphere``
        (the correspondences are taken to the viewing sphere first), else None (their image positions)."""
        return self.camera_hfov_deg if self.looming_on_sphere else None


class HippomapConfig(_Frozen):
    """All of hippomap's model parameters."""

    spatial: SpatialConfig = SpatialConfig()
    visual: VisualConfig = VisualConfig()
    map: MapConfig = MapConfig()
    mapper: MapperConfig = MapperConfig()

    @model_validator(mode="after")
    def _check(self) -> "HippomapConfig":
        p, bar = self.mapper.sequence_prior, self.visual.decision_threshold
        if p is not None and not p < bar:
            raise ValueError(f"mapper.sequence_prior ({p:g}) must be below visual.decision_threshold ({bar:g})")
        return self

    @classmethod
    def with_overrides(cls, overrides: dict[str, Any] | None = None) -> "HippomapConfig":
        """Defaults updated by a nested dict, e.g. ``{"map": {"alpha": 0.3}}``; validated."""
        base = cls().model_dump()
        for section, values in (overrides or {}).items():
            if section not in base:
                raise ValueError(f"unknown config section {section!r}; known: {sorted(base)}")
            if not isinstance(values, dict):
                raise ValueError(f"config section {section!r} must be a mapping")
            base[section].update(values)
        return cls.model_validate(base)

    @classmethod
    def from_file(cls, path: str | None) -> "HippomapConfig":
        """Defaults, or defaults updated by a JSON file of nested overrides."""
        import json
        from pathlib import Path

        from .errors import InputError

        if not path:
            return cls()
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read config {path}: {exc}") from exc
        try:
            return cls.with_overrides(data)
        except ValueError as exc:
            raise InputError(f"invalid config {path}: {exc}") from exc
