"""End to end through the command line: a short run writes every result file."""

import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sim.cli import app
from sim.scenario import load_scenario

QUICKSTART = Path(__file__).parents[1] / "scenarios" / "quickstart.yaml"
runner = CliRunner()


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0, result.output
    assert result.output == f"marsyard {importlib.metadata.version('marsyard')}\n"


def test_validate_ok_and_bad_key(tmp_path):
    ok = runner.invoke(app, ["validate", str(QUICKSTART)])
    assert ok.exit_code == 0, ok.output
    bad = runner.invoke(app, ["validate", str(QUICKSTART), "--set", "robots.lru1.camera.widht=100"])
    assert bad.exit_code == 2
    assert "robots.0(lru1).camera.widht: unknown key" in bad.output


def test_short_run_writes_every_result_file(tmp_path):
    out = tmp_path / "run"
    result = runner.invoke(
        app,
        ["run", str(QUICKSTART), "--out", str(out), "--seed", "5", "--set", "duration_s=2", "--no-progress"],
    )
    assert result.exit_code == 0, result.output
    robots = ["lru1", "lru2", "ardea"]
    expected = ["scenario.yaml", "metrics.json", "stereo_depth_error.csv", "lanes.csv", "routes.csv", "topdown.png", "recording.rrd"]
    expected += [f"trajectories/{r}.gt.tum" for r in robots] + [f"sensors/{r}.npz" for r in robots]
    for name in expected:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert not (out / "error.txt").exists()

    resolved = load_scenario(out / "scenario.yaml")
    assert resolved.seed == 5 and resolved.duration_s == 2

    # the recording: JPEG camera images, uint16 depth, a default blueprint (read back by rerun's own CLI)
    rerun = Path(sys.executable).parent / "rerun"
    printed = subprocess.run([rerun, "rrd", "print", out / "recording.rrd"], capture_output=True, text=True, check=True)
    chunks = printed.stdout.splitlines()
    assert any("/cameras/lru1/head/left - data columns: [EncodedImage:blob EncodedImage:media_type]" in c for c in chunks)
    depth = [c for c in chunks if "/cameras/lru1/head/depth - data columns" in c]
    assert depth and all("DepthImage:format" in c for c in depth)
    assert any("ViewBlueprint" in c for c in chunks)

    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "completed"
    assert metrics["runtime"]["sim_s"] == pytest.approx(2.0, abs=0.2)
    assert metrics["runtime"]["real_time_factor"] > 0
    for r in robots:
        m = metrics["robots"][r]
        assert m["camera_frames"] >= 10  # 5 Hz for 2 s, first frame at t = 0
        assert m["lane"]["stages"]["stereo"]["completed"] > 0
    lc = metrics["loop_closures"]  # evaluated, not failed (a failure leaves a status)
    assert set(lc["robots"]) == set(robots) and "status" not in lc
    assert lc["robots"]["lru1"]["matches"]["mode"] == "4d" and lc["team"]["matches"] == 0
    tum = np.loadtxt(out / "trajectories" / "lru1.gt.tum")
    assert tum.shape[1] == 8 and np.allclose(np.linalg.norm(tum[:, 4:], axis=1), 1, atol=1e-6)
    sensors = np.load(out / "sensors" / "lru1.npz")
    assert sensors["imu"].shape[1] == 6 and len(sensors["imu_t"]) >= 2 * 200
    assert len(sensors["odom_t"]) >= 2 * 50
