"""The typed query port (hippomap/mapper_queries.py): reads of a mapper are values naming one of a
fixed set of operations; anything else is refused with an error that names it, in the model, in
every host and in the session worker, before it runs."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from hippomap import mapper_queries as mq
from hippomap.config import HippomapConfig
from hippomap.errors import InputError
from hippomap.inputs import Frame, Odometry
from hippomap.mapper import Mapper
from server.runtime.mapper_host import InProcessHost
from tests.support.synthetic import decoded, synthetic_inputs

CONFIG = HippomapConfig.with_overrides({"mapper": {"keyframe_interval": 3}, "spatial": {"resolution_m": 0.004}})


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    m = Mapper(CONFIG)
    for v in decoded(synthetic_inputs(n_odometry=240, frame_every=3)):
        m.step(v) if isinstance(v, Odometry) else m.observe(v)
    assert isinstance(v, (Odometry, Frame)) and m.stats()["recognitions"] > 0
    return m


def test_unknown_operations_are_refused_naming_the_known_ones(mapper):
    with pytest.raises(InputError, match=r"unknown mapper query operation 'nosuch'; known: .*trajectory"):
        mq.query_named("nosuch")
    with pytest.raises(InputError, match=r"takes no argument\(s\) \['bogus'\]"):
        mq.query_named("stats", bogus=1)
    with pytest.raises(InputError, match="unknown mapper query"):  # a function is not a query
        mapper.answer(lambda m: m.cmap)  # type: ignore[arg-type]

    class Sneaky(mq.Stats):  # a subclass would run its own code in the mapper's process
        def run(self, m):
            return m.to_bytes()

    with pytest.raises(InputError, match="unknown mapper query"):
        mapper.answer(Sneaky())
    host = InProcessHost()
    host.restore(None, CONFIG)
    with pytest.raises(InputError, match="unknown mapper query"):
        host.query("stats")  # type: ignore[arg-type]


def test_bad_arguments_are_refused_when_the_query_is_made():
    with pytest.raises(InputError, match="trajectory source must be 'map' or 'odometry'"):
        mq.Trajectory("groundtruth")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="limit must be an integer >= 0"):
        mq.Recognitions(-1, -5)
    with pytest.raises(InputError, match="id must be an integer >= 0"):
        mq.query_named("recognition", id="3")


def test_every_operation_answers_from_the_mapper_and_pickles_without_closures(mapper):
    """Each query is a plain value (the standard pickle carries it) and answers what the mapper holds."""
    for op, cls in mq.QUERY_TYPES.items():
        assert cls.op == op
    queries = [mq.query_named(op) for op in mq.QUERY_TYPES if op != "recognition"] + [mq.RecognitionById(0)]
    for q in queries:
        assert pickle.loads(pickle.dumps(q)) == q
    assert mapper.answer(mq.Stats()) == mapper.stats()
    t, poses = mapper.answer(mq.Trajectory("odometry"))
    assert len(t) == len(poses) == mapper.stats()["odometry_steps"]
    np.testing.assert_array_equal(poses, mapper.odometry_trajectory())
    recs = mapper.answer(mq.Recognitions(0, 2))
    assert [r["id"] for r in recs] == [1, 2][: len(recs)]
    assert mapper.answer(mq.RecognitionById(10**6)) is None
    assert mapper.answer(mq.RecognitionById(0)) == mapper.recognitions[0]
    arrays = mapper.answer(mq.GraphArrays(information=True))
    assert len(arrays["poses"]) == mapper.stats()["nodes"] and len(arrays["information"]) == mapper.stats()["links"]
    view = mapper.answer(mq.ViewerState(4))
    assert view.trajectory_start == 4 and len(view.trajectory) == mapper.stats()["odometry_steps"] - 4
    assert view.recognition_count == len(mapper.recognitions) and view.place_code is mapper.place_field
    assert mapper.answer(mq.ViewerState(10**6)).trajectory_start == 0  # beyond the history: from the start
    assert Mapper.from_bytes(mapper.answer(mq.MapperState())).stats() == mapper.stats()
    assert Mapper.from_bytes(mapper.answer(mq.BaseSnapshot({}))).base_nodes == mapper.stats()["nodes"]
