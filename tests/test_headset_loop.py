"""``viotb headset --loop-closure``: the closer beside the headset's estimator, a map saved and reloaded."""

from __future__ import annotations

import csv
import json

import numpy as np
from typer.testing import CliRunner
from viotb.envs.run.loop_glue import CSV_COLUMNS
from viotb.envs.tools.cli import app


def _run(out, *args):
    return CliRunner().invoke(
        app, ["headset", "headset-walk", "--seconds", "3", "--out", str(out), "--json", *args]
    )


def test_headset_loop_closure_needs_images(tmp_path):
    res = _run(tmp_path / "a", "--frontend", "sim", "--loop-closure")
    assert res.exit_code == 2 and "camera images" in res.output
    res = _run(tmp_path / "b", "--frontend", "sim", "--map-out", str(tmp_path / "m.npz"))
    assert res.exit_code == 2 and "--loop-closure" in res.output


def test_headset_loop_closure_writes_the_csv_and_a_map_a_second_session_loads(tmp_path):
    """Walking the room on rendered images: keyframes go into the map; the saved map loads in a new session.

    Until a closure the corrected pose is the estimate: with none, online ATE = odometry ATE.
    """
    map_path = tmp_path / "room.npz"
    res = _run(tmp_path / "first", "--loop-closure", "--map-out", str(map_path))
    assert res.exit_code == 0, res.output
    result = json.loads(res.output.strip().splitlines()[-1])
    assert result["loop_keyframes"] > 0 and result["loop_closures"] == len(
        list(csv.reader((tmp_path / "first" / "loop_closures.csv").open()))[1:]
    )
    header = next(csv.reader((tmp_path / "first" / "loop_closures.csv").open()))
    assert tuple(header) == CSV_COLUMNS
    if result["loop_closures"] == 0:
        assert np.isclose(result["ate_posyaw_online_m"], result["ate_posyaw_odometry_m"])
    assert map_path.is_file()
    again = _run(tmp_path / "second", "--loop-closure", "--map-in", str(map_path))
    assert again.exit_code == 0, again.output
    second = json.loads(again.output.strip().splitlines()[-1])
    assert second["loop_keyframes"] > result["loop_keyframes"]  # the loaded room plus this session's
    # The second session walks the same scripted path: it recognizes the room from the start, and a closure
    # between the same instant of the two sessions relates two identical true poses (truth: identity).
    assert second["relocalizations"] >= 1
    rows = list(csv.DictReader((tmp_path / "second" / "loop_closures.csv").open()))
    same_instant = [r for r in rows if abs(float(r["t_query_s"]) - float(r["t_match_s"])) < 1e-6]
    assert same_instant
    for r in same_instant:
        assert np.linalg.norm([float(r[a]) for a in "xyz"]) < 0.03
        assert 2 * np.degrees(np.arccos(min(1.0, abs(float(r["qw"]))))) < 1.0
