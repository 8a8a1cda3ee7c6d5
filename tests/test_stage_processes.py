"""The front end and mapping in their own processes give exactly the inline results, and a failure or an
interrupt on either side ends the run cleanly: the error surfaces in the caller and no child is left behind."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pytest

from core.errors import GpslamError
from core.frame import Frame
from evaluation.sim import LASER_PRESETS, load_world, simulate
from slam.logs import open_log
from slam.logs.simulated import write_simulated_log
from slam.pipeline.config import SlamConfig
from slam.pipeline.front_process import FrontEndProcess
from slam.pipeline.run import run_slam

pytestmark = pytest.mark.xdist_group("pipeline")


@pytest.fixture(scope="module")
def sim_log(tmp_path_factory):
    """900 scans of the corridor world, whose tour returns to its earlier passes: enough keyframes and
    closures to exercise the hand-over (a shorter tour stands and turns near its start, and the robot's
    own pass is no loop)."""
    d = tmp_path_factory.mktemp("sim")
    sim = simulate(load_world("corridor"), n_scans=900, spec=LASER_PRESETS["hokuyo_utm30"], seed=7)
    path = d / "corridor.mcap"
    write_simulated_log(sim, path)
    return path


def _run(path, process: bool, map_method: str = "fastgpom"):
    cfg = SlamConfig.model_validate({"stage_processes": process, "mapping": {"params": {"method": map_method}}})
    return run_slam(open_log(path).frames(), cfg)


@pytest.mark.parametrize("map_method", ["fastgpom", "logodds"])
def test_stage_processes_and_inline_give_identical_results(sim_log, map_method):
    """Same keyframes, odometry, closures, optimised poses and map, bit for bit: the back half consumes
    the keyframes in the same order either way, and the mapping process gets the same calls (online
    submaps, or the baseline built at the end from every keyframe)."""
    a, b = _run(sim_log, False, map_method), _run(sim_log, True, map_method)
    assert len(a.keyframes) == len(b.keyframes) > 10
    assert len(a.loops) == len(b.loops) > 0
    for x, y in zip(a.keyframes, b.keyframes):
        assert x.scan_index == y.scan_index and np.array_equal(x.points, y.points)
    assert np.array_equal(a.odometry, b.odometry)
    assert np.array_equal(a.poses, b.poses)
    assert np.array_equal(a.occupancy_map.probability, b.occupancy_map.probability)
    assert a.odometry_stats == b.odometry_stats
    assert a.map_scans_fused == b.map_scans_fused == len(a.keyframes)
    assert set(b.peak_memory_mb) == {"front_end", "mapping"} and a.peak_memory_mb == {}
    assert not mp.active_children()


def _frames_then(path, failure: BaseException, after: int):
    for k, frame in enumerate(open_log(path).frames()):
        if k == after:
            raise failure
        yield frame


@pytest.mark.parametrize("failure", [KeyboardInterrupt(), GpslamError("corrupt.clf: line 9: bad range")])
def test_an_interrupt_or_a_bad_log_stops_the_child(sim_log, failure):
    """Ctrl-C or a corrupt record while the child is running: the caller sees that exception, and the
    front-end process is gone."""
    with pytest.raises(type(failure), match=str(failure) or None):
        run_slam(_frames_then(sim_log, failure, after=120), SlamConfig())
    assert not mp.active_children()


def test_a_failure_in_the_child_is_raised_in_the_parent():
    """A frame the front end cannot process (a 3D cloud after planar scans) fails in the child; the parent
    raises it with the child's message instead of waiting for ever."""
    ang = np.linspace(-1.5, 1.5, 181)
    rng = np.full(181, 4.0)
    planar = Frame(0.0, np.c_[rng * np.cos(ang), rng * np.sin(ang)], 0, ang, rng, np.zeros(181, bool))
    front = FrontEndProcess(SlamConfig(), planar=True)
    try:
        front.submit(planar)
        front.submit(Frame(0.1, np.ones((5, 3)), 1))
        with pytest.raises(GpslamError, match=r"shape \(5, 3\)"):
            front.finish()
    finally:
        front.close()
    assert not mp.active_children()
