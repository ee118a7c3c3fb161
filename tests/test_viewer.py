"""The step viewer (report) and the run animation (``mmslam slam --animate``).

Facts checked: the frames hold exactly the run's positions, estimates and GOSPA per step and the
cache's paths as BS -> first bounce -> receiver polylines (a hand-built run and paths table); the
HTML fragment is self-contained and carries the data losslessly; the JavaScript renderer, run in
Node, draws one element per path / estimate at the pixel the data says (cross-checked against an
independent Python mapping); in headless Chromium the page's script fills the frame; the animation
has one frame per step and is tagged as mmslam's; file targets are checked before any work.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mmslam.errors import MmslamError
from mmslam.model import BS, OTHER, SP, VA
from mmslam.slam.eval.viewer import (ANIMATION_FORMATS, VIEWER_JS, animate, check_animation_target, viewer_data,
                                     viewer_html)
from mmslam.scenes import load_preset
from mmslam.slam.filter.result import Result

NAMES = ["veh1", "veh2"]


def _result() -> Result:
    """Two vehicles, three steps; fused + local maps; hand-chosen numbers."""
    steps = np.repeat(np.arange(3), 2).astype(np.int32)
    veh = np.tile(np.arange(2), 3).astype(np.int16)
    tx = np.array([10.0, 20.0, 11.0, 21.0, 12.0, 22.0])
    ty = np.array([0.0, 5.0, 1.0, 6.0, 2.0, 7.0])
    vehicles = {"step": steps, "vehicle": veh, "x": tx + 0.5, "y": ty - 0.25, "z": np.zeros(6),
                "true_x": tx, "true_y": ty, "true_z": np.zeros(6), "pos_err": np.full(6, 0.5590169943749475)}
    landmarks = {"step": np.array([0, 2, 2, 2], np.int32), "map": np.array(["fused", "fused", "fused", "veh1"]),
                 "type": np.array(["VA", "VA", "VS", "SP"]), "x": np.array([200.0, 199.0, 20.5, 55.0]),
                 "y": np.array([0.0, 1.0, 7.2, 55.0]), "z": np.zeros(4), "weight": np.array([0.9, 0.8, 0.7, 0.6])}
    metrics = {"step": np.array([2, 2, 1], np.int32), "map": np.array(["fused", "fused", "veh2"]),
               "type": np.array(["VA", "VS", "SP"]), "gospa": np.array([1.234, 20.0, 3.0])}
    return Result(vehicles, metrics, landmarks, {"variant": "proposed", "seed": 7, "particles": 5,
                                                 "vehicle_names": NAMES})


def _paths() -> dict[str, np.ndarray]:
    """Step 0: LOS + one VA bounce to veh1; step 2: an SP bounce to veh2, an OTHER path to veh1."""
    nan = np.nan
    return {"step": np.array([0, 0, 2, 2], np.int32), "rx": np.array([0, 0, 1, 0], np.int16),
            "type": np.array([BS, VA, SP, OTHER], np.int8),
            "landmark_id": np.array(["bs", "wall_east:-x", "sp1", "a+b"], object),
            "bounce_x": np.array([nan, 100.0, 55.0, 30.0]), "bounce_y": np.array([nan, 3.0, 55.0, -4.0]),
            "lm_x": np.array([0.0, 200.0, 55.0, nan]), "lm_y": np.array([0.0, 0.0, 55.0, nan]),
            "lm_z": np.array([40.0, 40.0, 12.5, nan])}


@pytest.fixture(scope="module")
def data() -> dict:
    return viewer_data(_result(), load_preset("paper"), _paths())


def test_frames_hold_the_runs_positions_estimates_and_gospa(data: dict) -> None:
    assert data["steps"] == [0, 1, 2]
    v1, v2 = data["vehicles"]
    assert v1["name"] == "veh1" and v1["true"] == [[10.0, 0.0], [11.0, 1.0], [12.0, 2.0]]
    assert v2["est"] == [[20.5, 4.75], [21.5, 5.75], [22.5, 6.75]]
    assert v1["err"] == [0.56, 0.56, 0.56]  # rounded to 1 cm
    assert data["maps"] == ["fused", "veh1", "veh2"]
    assert data["estimates"]["fused"] == [[["VA", 200.0, 0.0, 0.9]], [], [["VA", 199.0, 1.0, 0.8],
                                                                           ["VS", 20.5, 7.2, 0.7]]]
    assert data["estimates"]["veh1"][2] == [["SP", 55.0, 55.0, 0.6]] and data["estimates"]["veh2"] == [[], [], []]
    assert data["gospa"]["fused"]["VA"] == [None, None, 1.23] and data["gospa"]["fused"]["VS"][2] == 20.0
    assert data["gospa"]["veh2"]["SP"] == [None, 3.0, None]
    assert data["bs"] == [0.0, 0.0]


def test_paths_are_bs_bounce_receiver_polylines(data: dict) -> None:
    p0, p1, p2 = data["paths"]
    assert p0 == [[0, "BS", [[0.0, 0.0], [10.0, 0.0]]], [0, "VA", [[0.0, 0.0], [100.0, 3.0], [10.0, 0.0]]]]
    assert p1 == []
    assert p2 == [[1, "SP", [[0.0, 0.0], [55.0, 55.0], [22.0, 7.0]]],
                  [0, "OTHER", [[0.0, 0.0], [30.0, -4.0], [12.0, 2.0]]]]
    # truth of the seen landmarks, one per id (OTHER has none)
    assert data["truth"] == {"VA": [[200.0, 0.0, 40.0]], "SP": [[55.0, 55.0, 12.5]]}
    x0, x1, y0, y1 = data["bounds"]
    for x, y in [(200.0, 0.0), (55.0, 55.0), (0.0, 0.0), (10.0, 0.0), (22.5, 6.75)]:
        assert x0 < x < x1 and y0 < y < y1


def test_without_a_cache_the_truth_is_the_scenarios() -> None:
    from mmslam.scenes.landmarks import sp_truth, va_truth

    scn = load_preset("paper")
    d = viewer_data(_result(), scn, None)
    assert d["paths"] is None
    assert len(d["truth"]["VA"]) == len(va_truth(scn)) == 4 and len(d["truth"]["SP"]) == len(sp_truth(scn))
    assert sorted(tuple(p[:2]) for p in d["truth"]["VA"]) == [(-200.0, 0.0), (0.0, -200.0), (0.0, 200.0),
                                                              (200.0, 0.0)]


def test_html_fragment_is_self_contained_and_lossless(data: dict) -> None:
    frag = viewer_html(data, element_id="v1")
    blob = re.search(r'<script type="application/json" class="viewer-data">(.*?)</script>', frag, re.S).group(1)
    assert json.loads(blob) == json.loads(json.dumps(data))
    assert 'type="range" min="0" max="2" value="2"' in frag
    assert not re.search(r'(src|href)\s*=\s*["\']?(https?:)?//', frag)  # nothing fetched
    assert "mmslamFrameSVG" in frag and "mmslamFrameSVG" not in viewer_html(data, script=False)
    # a '</script>' inside the data cannot end the data element early
    evil = dict(data, title="</script><b>x")
    frag2 = viewer_html(evil, script=False)
    blob2 = re.search(r'class="viewer-data">(.*?)</script>', frag2, re.S).group(1)
    assert json.loads(blob2)["title"] == "</script><b>x"


def _node(script: str) -> str:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (Debian package nodejs); the renderer is checked in Chromium below")
    return subprocess.run([node, "-e", script], capture_output=True, text=True, check=True, timeout=60).stdout


def test_javascript_renderer_draws_each_path_and_estimate_where_the_data_says(data: dict, tmp_path: Path) -> None:
    (tmp_path / "viewer.js").write_text(VIEWER_JS)
    (tmp_path / "data.json").write_text(json.dumps(data))
    out = _node(f"const V = require({json.dumps(str(tmp_path / 'viewer.js'))});"
                f"const D = require({json.dumps(str(tmp_path / 'data.json'))});"
                "console.log(JSON.stringify([V.mmslamFrameSVG(D, 2, 'fused', true), V.mmslamFrameSVG(D, 0, 'veh1', false),"
                " V.mmslamFrameText(D, 2, 'fused')]));")
    svg2, svg0, text = json.loads(out)
    assert svg2.count('<polyline class="path"') == 2 and svg0.count('<polyline class="path"') == 0
    assert svg2.count('class="estimate"') == 2 and svg0.count('class="estimate"') == 0
    assert svg2.count('class="estimate" data-type="VS"') == 1
    x0, x1, y0, y1 = data["bounds"]
    W = 640
    H = round(W * (y1 - y0) / (x1 - x0))

    def px(x: float, y: float) -> tuple[str, str]:  # independent mapping: x east right, y north up
        return f"{(x - x0) / (x1 - x0) * W:.1f}", f"{(y1 - y) / (y1 - y0) * H:.1f}"

    cx, cy = px(22.0, 7.0)  # veh2's true position at step 2
    assert f'class="vehicle-true" data-vehicle="1" cx="{cx}" cy="{cy}"' in svg2
    sx, sy = px(55.0, 55.0)  # SP bounce of step 2's path
    assert re.search(rf'data-type="SP" data-rx="1" points="[^"]*{re.escape(sx)},{re.escape(sy)} ', svg2)
    assert text == "GOSPA VA 1.23 m | GOSPA VS 20.00 m | veh1 error 0.56 m | veh2 error 0.56 m | 2 traced paths"
    # the trajectories grow with the step: 1 point at step 0, 3 at step 2
    assert re.search(r'class="traj-true" data-vehicle="0" points="[^" ]+"', svg0)
    assert len(re.search(r'class="traj-true" data-vehicle="0" points="([^"]+)"', svg2).group(1).split()) == 3


def test_viewer_runs_in_headless_chromium(data: dict, tmp_path: Path) -> None:
    """The page's own script (DOMContentLoaded) draws the last step into the frame box."""
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("headless Chromium is not installed (Debian package chromium); the renderer is checked in Node")
    page = tmp_path / "v.html"
    page.write_text('<!DOCTYPE html><html><head><meta charset="utf-8"></head><body>'
                    + viewer_html(data) + "</body></html>")
    dom = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--dump-dom", page.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    box = re.search(r'<div class="frame-box">(.*?)</div>', dom, re.S)
    assert box and "<svg" in box.group(1) and box.group(1).count('class="path"') == 2
    assert "GOSPA VA 1.23 m" in dom


def test_animation_has_a_frame_per_step_and_is_tagged(data: dict, tmp_path: Path) -> None:
    from PIL import Image

    from mmslam.outputs import is_mmslam_figure

    p = animate(data, tmp_path / "run.gif", dpi=40)
    with Image.open(p) as im:
        assert im.format == "GIF" and im.n_frames == 3
    assert is_mmslam_figure(p)
    assert not list(tmp_path.glob(".run.gif.*"))  # no temporary left
    assert check_animation_target(p) == "gif"  # our own file may be replaced


def test_animation_target_is_checked_before_any_work(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    user = tmp_path / "mine.gif"
    user.write_bytes(b"GIF89a user data")
    for force in (False, True):  # --force never widens what may be touched
        with pytest.raises(MmslamError, match="a file mmslam did not write"):
            check_animation_target(user, force=force)
    assert user.read_bytes() == b"GIF89a user data"
    with pytest.raises(MmslamError, match=r"unknown figure format '\.png'.*\.gif, \.mp4"):
        check_animation_target(tmp_path / "a.png")
    with pytest.raises(MmslamError, match="does not exist"):
        check_animation_target(tmp_path / "nodir" / "a.gif")
    from matplotlib import animation

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    with pytest.raises(MmslamError, match="needs ffmpeg"):
        check_animation_target(tmp_path / "a.mp4")
    assert ANIMATION_FORMATS == ("gif", "mp4")


def test_slam_animate_cli(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``mmslam slam --animate`` on a tiny analytic cache: a GIF with one frame per step; a foreign
    file is refused before the filter runs (no result written)."""
    from PIL import Image

    from mmslam.cli import main

    assert main(["trace", "paper", "--source", "analytic", "--steps", "3", "--out", str(tmp_path / "c"),
                 "--quiet"]) == 0
    cache = next((tmp_path / "c").iterdir())
    user = tmp_path / "user.gif"
    user.write_bytes(b"not ours")
    code = main(["slam", str(cache), "--particles", "5", "--out", str(tmp_path / "r0"), "--animate", str(user)])
    assert code == 2 and not (tmp_path / "r0").exists() and user.read_bytes() == b"not ours"
    assert "--animate" in capsys.readouterr().err
    gif = tmp_path / "run.gif"
    assert main(["slam", str(cache), "--variant", "proposed", "--particles", "5", "--out", str(tmp_path / "r"),
                 "--animate", str(gif)]) == 0
    with Image.open(gif) as im:
        assert im.n_frames == 3
