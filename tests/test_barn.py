"""The BARN reader (jaxnav.io.barn), the challenge's score, and the converted suite in scenes/barn/.

No env is compiled here. Loading all 300 rooms validates each one (about 40 s on 2 cores), so that
test is marked slow.
"""

import json
import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import benchmark_script

import jaxnav
from jaxnav.core.assets import scenes_dir
from jaxnav.io import barn
from jaxnav.io.layouts import MAX_OBSTACLES, layout_to_dict, parse_layouts

SUITE = scenes_dir() / "barn"
WORLD_0 = SUITE / "sample" / "world_0.world.gz"  # BARN's world 0, unmodified
PATH_0 = SUITE / "sample" / "path_0.npy"
GROUPS = {"easy": range(0, 100), "medium": range(100, 200), "hard": range(200, 300)}


@pytest.fixture(scope="module")
def world_0() -> dict:
    return barn.world_layout(WORLD_0)


def test_read_world_finds_every_cylinder():
    cylinders = barn.read_world(WORLD_0)
    assert cylinders.shape == (209, 4)  # 209 unit_cylinder models in world_0.world
    # radius 0.075 m, 1 m long centred on the floor: 0.5 m above it
    np.testing.assert_allclose(cylinders[:, 2:], np.tile([0.075, 0.5], (209, 1)))


def test_world_layout_of_world_0(world_0):
    # Walls: 64 cylinders in each side column and 30 in the back row, 2 shared: 156 of 209.
    assert world_0["name"] == "world_0"
    assert len(world_0["obstacles"]) == 209 - 156
    # Interior: x from -4.35 to -0.15 (inner faces of the columns at -4.425 and -0.075), y from
    # 0.15 (back row at 0.075) to the goal's 13 + 2: centre (-2.25, 7.575) in BARN's frame.
    assert world_0["room"] == {"size": [4.2, 14.85], "wall_height": 0.5}
    assert world_0["robot"] == {"pos": [0.0, -4.575], "yaw": 1.5708}  # BARN's (-2.25, 3)
    assert world_0["goal"] == {"pos": [0.0, 5.425]}  # BARN's (-2.25, 13)
    # unit_cylinder_126 stands at (-4.275, 5.325) in BARN's frame: (-4.275 + 2.25, 5.325 - 7.575).
    ob = {"type": "cylinder", "pos": [-2.025, -2.25], "radius": 0.075, "height": 0.5}
    assert ob in world_0["obstacles"]


def test_world_layout_is_a_valid_layout(world_0):
    (room,) = parse_layouts(world_0)
    assert room.robot_pos == (0.0, -4.575) and room.goal_pos == (0.0, 5.425)


def test_wall_with_a_gap_is_refused():
    cylinders = barn.read_world(WORLD_0)
    west = np.flatnonzero(np.isclose(cylinders[:, 0], cylinders[:, 0].min()))
    holed = np.delete(cylinders, west[10], axis=0)
    with pytest.raises(ValueError, match="west column has gaps"):
        barn.split_walls(holed, "holed")


def test_optimal_path_length_by_hand():
    # Cells (15, 0) and (15, 29) sit at (-2.325, 5.075) and (-2.325, 9.425) as run.py maps them.
    length = barn.optimal_path_length(np.array([[15, 0], [15, 29]]))
    hand = math.hypot(0.075, 5.075 - 3.0) + (9.425 - 5.075) + math.hypot(0.075, 13.0 - 9.425)
    assert length == pytest.approx(hand, abs=1e-12)
    assert barn.optimal_time(length) == pytest.approx(hand / 2.0)


def test_optimal_path_length_of_world_0():
    path = np.load(PATH_0)
    points = (
        [(-2.25, 3.0)] + [(0.15 * i - 4.575, 0.15 * j + 5.075) for i, j in path] + [(-2.25, 13)]
    )
    hand = sum(math.dist(a, b) for a, b in zip(points[:-1], points[1:], strict=True))
    assert barn.optimal_path_length(path) == pytest.approx(hand, abs=1e-12)
    meta = json.loads((SUITE / "suite.json").read_text())["rooms"]
    assert meta["world_0"] == {"optimal_path_m": round(hand, 4), "difficulty_rank": 0}


@pytest.mark.parametrize(
    ("success", "time_s", "optimal_s", "score"),
    [
        (False, 10.0, 5.0, 0.0),  # failed: 0 whatever the time
        (0, float("nan"), 5.0, 0.0),  # a failed run's time may be missing
        (True, 6.0, 5.0, 0.5),  # under 2x optimal counts as 2x
        (True, 10.0, 5.0, 0.5),
        (True, 20.0, 5.0, 0.25),  # 4x
        (True, 40.0, 5.0, 0.125),  # 8x
        (True, 100.0, 5.0, 0.125),  # over 8x counts as 8x
    ],
)
def test_barn_score_by_hand(success, time_s, optimal_s, score):
    assert barn.barn_score(success, time_s, optimal_s) == pytest.approx(score)


def test_barn_score_on_arrays():
    out = barn.barn_score([1, 1, 0], [3.0, 12.0, 3.0], [2.0, 2.0, 2.0])
    np.testing.assert_allclose(out, [0.5, 2.0 / 12.0, 0.0])


def test_reader_imports_no_jax():
    code = "import sys, jaxnav.io.barn; print('jax' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_suite_files_hold_the_300_worlds_in_order():
    suite = json.loads((SUITE / "suite.json").read_text())
    assert (suite["score"], suite["time_limit_s"]) == ("barn", 100)
    meta = suite["rooms"]
    assert list(meta) == [f"world_{i}" for i in range(300)]
    for group, indices in GROUPS.items():
        rooms = json.loads((SUITE / f"{group}.json").read_text())
        assert [r["name"] for r in rooms] == [f"world_{i}" for i in indices]
        assert all(meta[f"world_{i}"]["difficulty_rank"] == i for i in indices)
        assert max(len(r["obstacles"]) for r in rooms) <= MAX_OBSTACLES
    assert "MIT License" in (SUITE / "LICENSE").read_text()


def test_suite_world_0_is_the_reader_output(world_0):
    (expected,) = parse_layouts(world_0)
    first = json.loads((SUITE / "easy.json").read_text())[0]
    (stored,) = parse_layouts(first)
    assert layout_to_dict(stored) == layout_to_dict(expected)


@pytest.mark.slow
def test_all_300_rooms_load():
    """Every BARN world loads with a start and a goal. Slow: 300 layouts parsed and validated."""
    rooms = [r for group in GROUPS for r in jaxnav.load_layout(SUITE / f"{group}.json")]
    assert len(rooms) == 300
    assert all(r.goal_pos is not None and r.robot_pos is not None for r in rooms)


def test_evaluate_reports_barn_scores_per_world_group_and_overall():
    """`evaluate --suite barn` adds BARN's score per world, per difficulty group and overall:
    hand-computed for two worlds (optimal paths 10 m and 12 m, 0.1 s steps)."""
    import types

    from jaxnav import evaluation as ev

    env = types.SimpleNamespace(robot=types.SimpleNamespace(max_linear_speed=0.5))
    rooms = [
        {  # 2 episodes: success in 300 steps (30 s), a collision
            "metrics": {"success": np.array([1.0, 0.0])},
            "steps": np.array([300, 50]),
            "control_period": 0.1,
            "collided": np.array([False, True]),
            "env": env,
        },
        {  # a timeout, and a success in 100 steps (10 s, under 2x the 6 s optimum)
            "metrics": {"success": np.array([0.0, 1.0])},
            "steps": np.array([1000, 100]),
            "control_period": 0.1,
            "collided": np.array([False, False]),
            "env": env,
        },
    ]
    meta = {"rooms": {"a": {"optimal_path_m": 10.0}, "b": {"optimal_path_m": 12.0}}}
    results = {"layouts": {"a": {}, "b": {}}, "families": {"easy": {}}, "overall": {}}
    ev._add_barn(results, rooms, ["a", "b"], {"easy": ["a", "b"]}, meta)
    a, b = results["layouts"]["a"], results["layouts"]["b"]
    assert a["barn_score"] == pytest.approx((5.0 / 30.0 + 0) / 2)  # 30 s is 6x the 5 s optimum
    assert b["barn_score"] == pytest.approx((0 + 0.5) / 2)
    assert a["barn_score_own_speed"] == pytest.approx((20.0 / 40.0 + 0) / 2)  # 10 m at 0.5 m/s
    assert (a["timeout_rate"], b["timeout_rate"]) == (0.0, 0.5)
    overall = (5.0 / 30.0 + 0.5) / 4
    assert results["overall"]["barn_score"] == pytest.approx(overall)
    assert results["families"]["easy"]["barn_score"] == pytest.approx(overall)


def test_a_suite_folder_keeps_its_own_data_beside_its_rooms(tmp_path, monkeypatch):
    from jaxnav import evaluation as ev

    folder = tmp_path / "mine"
    folder.mkdir()
    room = {"name": "r", "room": {"size": [3.0, 3.0]}, "robot": {"pos": [0.0, 0.0]}}
    (folder / "easy.json").write_text(json.dumps(room))
    (folder / "suite.json").write_text(json.dumps({"time_limit_s": 42.0, "rooms": {}}))
    monkeypatch.setattr(ev, "scenes_dir", lambda: tmp_path)
    assert list(ev.load_suite("mine")) == ["easy"]
    policy = types_policy()
    assert ev.default_steps("mine", policy) == 420 and ev.default_steps(None, policy) == 600
    # The twin takes its episode length from the same limit, at its policy file's 20 Hz.
    import types

    from jaxnav.cli import twin

    flags = dict(steps=None, episodes=1, seed=0, width=64, height=48, every_frame=False)
    fast = types.SimpleNamespace(control_period=0.05)
    assert twin._config(types.SimpleNamespace(suite="mine", **flags), fast).steps == 840
    assert twin._config(types.SimpleNamespace(suite=None, **flags), fast).steps == 600


def types_policy():
    import types

    return types.SimpleNamespace(env_kwargs={})


def test_failure_analysis_finds_the_cylinder_its_bearing_and_when_it_was_last_readable():
    """benchmarks/barn_failures.py on a hand-made record: a robot driving along +x at 0.05 m a step
    past a cylinder 0.3 m to its left, the collision at the step that ends beside it."""
    from types import SimpleNamespace

    module = benchmark_script("barn_failures")
    far = SimpleNamespace(pos=(5.0, -3.0), radius=0.1)
    post = SimpleNamespace(pos=(0.0, 0.3), radius=0.075)
    layout = SimpleNamespace(name="by-hand", obstacles=[far, post])
    env = SimpleNamespace(
        sensor=SimpleNamespace(fov=math.radians(60), range_min=0.6),
        robot=SimpleNamespace(camera_forward=-0.05),
    )
    steps, t = 60, 40
    x = -2.0 + 0.05 * np.arange(steps)  # [T]; x = 0 (the cylinder abeam) at step t
    qpos = np.stack([x, np.zeros(steps), np.zeros(steps)], -1)[:, None]  # [T, 1, 3]
    action = np.zeros((steps, 1), np.int32)
    action[t] = 2
    hit = np.zeros((steps, 1), bool)
    hit[t] = True
    rec = (qpos, action, np.full((steps, 1, 8), 8.0, np.float32), hit)
    (row,) = module.collisions(rec, [layout], 1, env)
    assert row["world"] == "by-hand" and row["step"] == t and row["actions"][-1] == 2
    assert row["bearing_deg"] == pytest.approx(90.0)
    # Last readable: within 30 degrees of the heading and 0.6 m from the camera, by hand.
    cx = x[t - 20 : t + 1] - 0.05  # the camera, behind the centre
    bearing = np.degrees(np.arctan2(0.3, 0.0 - x[t - 20 : t + 1]))
    depth = np.hypot(0.0 - cx, 0.3) - 0.075
    readable = np.flatnonzero((np.abs(bearing) < 30) & (depth >= 0.6))
    assert row["steps_since_readable"] == 20 - readable[-1] > 0
    counts = module.tallies([row], ("forward", "left", "right"))
    assert counts["bearing_deg"]["60-90"] == 0 and counts["bearing_deg"]["90-120"] == 1
    assert counts["action"] == {"forward": 0, "left": 0, "right": 1}


def test_failure_analysis_follows_a_person_who_walked_in():
    """benchmarks/barn_failures.py's analysis with moving cylinders (crowdnav.py --contacts): a
    robot standing at the origin facing +x, a person walking from 2 m ahead to its left side;
    the bearing and when it was last readable come from where the person was at each step, not
    from where the layout put it."""
    from types import SimpleNamespace

    module = benchmark_script("barn_failures")
    layout = SimpleNamespace(name="walk", obstacles=[SimpleNamespace(pos=(2.0, 0.0), radius=0.25)])
    env = SimpleNamespace(
        sensor=SimpleNamespace(fov=math.radians(60), range_min=0.6),
        robot=SimpleNamespace(camera_forward=-0.05),
    )
    steps, t = 30, 25
    qpos = np.zeros((steps, 1, 3))
    walk = np.minimum(np.arange(steps), t) / t  # [T] 0 -> 1 at the collision, then it stands
    path = np.stack([2.0 * (1 - walk), 0.45 * walk], -1)  # [T, 2]
    hit = np.zeros((steps, 1), bool)
    hit[t] = True
    rec = (qpos, np.zeros((steps, 1), np.int32), np.full((steps, 1, 8), 8.0), hit)
    (still,) = module.collisions(rec, [layout], 1, env)
    assert still["bearing_deg"] == 0.0 and still["steps_since_readable"] == 0
    (row,) = module.collisions(rec, [layout], 1, env, moving=path[:, None, None])
    assert row["bearing_deg"] == pytest.approx(90.0)
    seen = path[t - 20 : t + 1]  # by hand: within 30 degrees and 0.6 m of the camera
    bearing = np.degrees(np.arctan2(seen[:, 1], seen[:, 0]))
    depth = np.hypot(seen[:, 0] + 0.05, seen[:, 1]) - 0.25
    readable = np.flatnonzero((np.abs(bearing) < 30) & (depth >= 0.6))
    assert row["steps_since_readable"] == 20 - readable[-1] > 0
