"""`jaxnav.viz.render` and `python -m jaxnav.evaluate --video`: GIFs of an episode, or PNGs without GL.

One short evaluation (one rollout compile) feeds every test; the CLI tests reuse its results.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from matplotlib.figure import Figure
from PIL import Image

import jaxnav
import jaxnav.cli.evaluate
from jaxnav.core.randomize import layout_grid_size, make_bank
from jaxnav.core.scene import SCENES_DIR
from jaxnav.evaluation import load_suite
from jaxnav.policy import forward_policy
from jaxnav.viz import plots, render

STEPS = 12


@pytest.fixture(scope="module")
def room():
    return jaxnav.load_layout(SCENES_DIR / "inference_room.json")


@pytest.fixture(scope="module")
def results(room):
    # The inference room's spawn faces a cylinder: the forward baseline drives straight at it.
    return jaxnav.evaluate(forward_policy(), room, episodes=2, steps=STEPS, seed=0)


@pytest.fixture(scope="module")
def episode(results, room):
    return results["_trajectories"][room[0].name]


def test_evaluate_keeps_the_first_episode(episode):
    qpos, paths = episode["qpos"], episode["paths"]
    assert qpos.shape == (len(paths[0]), 3)  # trimmed like the first path
    np.testing.assert_allclose(qpos[:, :2], paths[0], atol=1e-6)
    np.testing.assert_allclose(qpos[0], episode["params"].spawn, atol=1e-6)
    assert episode["params"].box_pos.ndim == 2  # one episode's params, no batch axis


def test_room_shapes_are_the_same_from_a_layout_and_from_its_scene_params(room, episode):
    from_layout, from_params = plots.room_shapes(room[0]), plots.room_shapes(episode["params"])
    assert from_layout.walls.shape == (4, 2, 2) and from_layout.boxes.shape == (4, 4, 2)
    assert from_layout.circles.shape == (4, 3)
    for field in ("walls", "boxes", "circles", "spawn"):
        expected = getattr(from_layout, field)
        np.testing.assert_allclose(getattr(from_params, field), expected, atol=1e-5, err_msg=field)
    np.testing.assert_allclose(from_layout.outer_half, [2.6, 3.6])  # 5 x 7 m room, 0.1 m walls


def test_grid_cells_are_drawn_as_boxes():
    """A dense field's occupied cells are boxes of the picture, the same from the layout and from
    its scene params (`grid.cell_boxes`)."""
    (field,) = [r for r in load_suite("hard")["dense_field"] if r.name == "dense_field-2"]
    bank = make_bank([field], 4, 4, grid=layout_grid_size([field]))
    params = jax.tree_util.tree_map(lambda x: x[0], bank.rooms)
    from_layout, from_params = plots.room_shapes(field), plots.room_shapes(params)
    occupied = sum(row.count("#") for row in field.grid.rows)
    assert occupied > 100 and from_layout.boxes.shape == (occupied, 4, 2)
    np.testing.assert_allclose(from_params.boxes, from_layout.boxes, atol=1e-5)
    side = from_layout.boxes[:, 2] - from_layout.boxes[:, 0]  # [N, 2] each cell's diagonal
    np.testing.assert_allclose(side, field.grid.cell, atol=1e-6)


def test_draw_room_takes_a_layout_or_scene_params(room, episode):
    fig = Figure()
    for ax, source in zip(fig.subplots(1, 2), (room[0], episode["params"]), strict=True):
        plots.draw_room(ax, source)
        assert len(ax.patches) == 4 + 4 + 4 + 1  # walls, boxes, cylinders, spawn disc
    batch = jax.tree_util.tree_map(lambda x: x[None], episode["params"])
    with pytest.raises(ValueError, match="no batch axis"):
        plots.room_shapes(batch)


def test_render_episode_writes_an_animated_gif(needs_gl, episode, tmp_path):
    path = render.render_episode(
        episode["env"], episode["params"], episode["qpos"], tmp_path / "ep.gif", 160, 120, fps=5
    )
    gif = Image.open(path)
    assert gif.format == "GIF" and gif.n_frames == len(episode["qpos"])
    assert gif.size == (2 * 160, 120)  # top-down view + the robot's camera
    assert gif.info["duration"] == 200
    first = np.asarray(gif.convert("RGB"))
    gif.seek(gif.n_frames - 1)
    last = np.asarray(gif.convert("RGB"))
    assert first.std() > 10  # a picture, not a blank frame
    assert np.abs(first.astype(int) - last).mean() > 1  # the robot moved, its view changed


def test_render_top_down_only(needs_gl, episode, tmp_path):
    qpos = episode["qpos"][:2]
    path = render.render_episode(
        episode["env"], episode["params"], qpos, tmp_path / "top.gif", 96, 80, robot_view=False
    )
    assert Image.open(path).size == (96, 80)


def test_render_episode_rejects_bad_poses(episode, tmp_path):
    with pytest.raises(ValueError, match="qpos_seq"):
        render.render_episode(episode["env"], episode["params"], np.zeros((5, 2)), tmp_path / "x")


def _cli(results, monkeypatch, tmp_path, capsys):
    """`evaluate --video` in-process on the module's results (no second rollout compile)."""
    monkeypatch.setattr(jaxnav.cli.evaluate, "evaluate", lambda *args, **kwargs: results)
    argv = ["--policy", "forward", "--plots", tmp_path / "plots", "--video", tmp_path / "video"]
    code = jaxnav.cli.evaluate.main([str(a) for a in argv])
    return code, capsys.readouterr()


def test_cli_video(needs_gl, results, room, monkeypatch, tmp_path, capsys):
    code, out = _cli(results, monkeypatch, tmp_path, capsys)
    assert code == 0, out.err
    gif = Image.open(tmp_path / "video" / f"{room[0].name}.gif")
    assert gif.n_frames == len(results["_trajectories"][room[0].name]["qpos"])
    assert "video: " in out.out and "GIF" in out.out


def test_cli_video_without_gl_writes_pngs(results, room, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(render, "gl_backend", lambda: None)
    code, out = _cli(results, monkeypatch, tmp_path, capsys)
    assert code == 0, out.err
    line = "video: no OpenGL backend (install libegl1 or libosmesa6); top-down PNGs written instead"
    assert line in out.out.splitlines()
    png = tmp_path / "video" / f"{room[0].name}.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((tmp_path / "video").glob("*.gif"))
