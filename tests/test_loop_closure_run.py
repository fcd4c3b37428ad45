"""A loop closure inside the run loop (thesis 6.1): a rover drives a leg through a rock
field, a loop, and the same leg again; the submaps it rendered on the two passes are
paired and matched by its lane's background jobs, and the accepted closure agrees with
the true relative pose of the two submap origins (``metrics.json`` ``loop_closures``)."""

from pathlib import Path

import pytest
import yaml
from metrics_util import without_timings

from sim.run.run_folder import run_to_folder
from sim.scenario import load_scenario

ETNA = Path(__file__).resolve().parents[1] / "scenarios" / "etna_two_rovers.yaml"
REVISIT = {
    "name": "revisit",
    "seed": 4,
    "duration_s": 150,
    "terrain": {
        "preset": "moon",
        "size_m": 24,
        "roughness_m": 0.03,
        "craters": {"count": 0},
        "rocks": {"count": 250, "diameter_m": [0.3, 1.0], "power_law_exponent": 2.0, "clearance_m": 0.6},
    },
    "robots": [
        {
            "name": "lru1",
            "preset": "lru",
            "start": {"xy": [-7, -2], "yaw_deg": 0},
            "route": {"speed_mps": 0.3, "waypoints": [[0, -2], [0, 1.5], [-7, 1.5], [-7, -2], [0, -2]]},
        }
    ],
    # the matcher as scenarios/etna_two_rovers.yaml sets it (salient keypoints besides the obstacles, sigmas widened as
    # the graph is overconfident, spin images, votes over yaw): at a46b171 it closed this revisit on seeds 4-7 within
    # 12 cm. Hough3D's votes, the default, closed it on seeds 5 and 6 but found no hypothesis on seed 4 after a fresh
    # set-up on 2026-12-07, where they had closed it before (docs/matching.md, "Voting without reference frames")
    "slam": {"mapping": {"submap_distance_m": 7.0}, "matching": yaml.safe_load(ETNA.read_text())["slam"]["matching"]},
    "output": {"recording": False, "topdown_png": False},
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The revisit with its matching on the background thread beside the loop, and inline (sim/run/pipeline.py)."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("MARSYARD_BACKGROUND_THREAD", "1")
        threaded = run_to_folder(load_scenario(REVISIT), tmp_path_factory.mktemp("threaded"), image_workers=1)
    return threaded, run_to_folder(load_scenario(REVISIT), tmp_path_factory.mktemp("inline"), image_workers=0)


@pytest.fixture(scope="module")
def metrics(runs):
    return runs[0]


def test_matching_beside_the_loop_gives_what_matching_inline_gives(runs):
    """The attempts run on the background thread while the loop goes on; every metric but wall times is the same."""
    assert runs[0]["runtime"]["image_thread_s"]["matching"] > 0 and "matching" not in runs[1]["runtime"]["image_thread_s"]
    threaded, inline = (without_timings(m) for m in runs)
    assert threaded["loop_closures"]["robots"]["lru1"]["matches"]["attempts"] > 0
    assert threaded == inline


def test_the_revisit_closes_a_correct_loop(metrics):
    assert metrics.get("error") is None
    matches = metrics["loop_closures"]["robots"]["lru1"]["matches"]
    assert matches["matches"] >= 1, matches
    assert matches["wrong_matches"] == 0
    errors = [m["error_m"] for m in matches["matches_list"]]
    assert max(errors) < 0.3
    # the closure relates the first pass to the second: submaps far apart in the route
    assert any(abs(int(m["a"].split(":")[1]) - int(m["b"].split(":")[1])) >= 2 for m in matches["matches_list"])
