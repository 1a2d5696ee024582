"""People who walk: reactive walkers give way and non-reactive ones do not, walkers reach their
goals at their speeds, the sampler's walkers start clear, collisions are attributed, the
circle-crossing layouts cross, and nothing recompiles between episodes."""

import dataclasses
import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import EXACT, XLA_CPU_CODE, benchmark_script, traced_once

import jaxnav
from jaxnav.core import crowd, motion
from jaxnav.core.geometry import signed_distance
from jaxnav.core.randomize import make_bank
from jaxnav.core.scene import SCENES_DIR
from jaxnav.core.sensors import SensorConfig
from jaxnav.evaluation import declared_values, eval_randomize, pooled
from jaxnav.io.layouts import (
    Cylinder,
    LayoutError,
    Motion,
    RoomLayout,
    layout_to_dict,
    load_layout,
    parse_layouts,
)
from jaxnav.tasks.base import WALKER_EVAL_METRICS, success_unhit

DT = 0.1  # s, the control period
ROBOT = 0.177  # m, the TurtleBot's radius
CROWDNAV = SCENES_DIR / "crowdnav"


def _walker(pos, goal, reactive=True, radius=0.25, speed=1.0, repeat=False) -> Cylinder:
    walk = Motion(goal=goal, speed=speed, reactive=reactive, repeat=repeat)
    return Cylinder(pos=pos, radius=radius, height=1.7, motion=walk)


def _room(*walkers, size=(8.0, 3.0), name="w") -> RoomLayout:
    return RoomLayout(name=name, size=size, robot_pos=(0.0, 0.0), obstacles=walkers)


def _params(layouts):
    """[K] the layouts' SceneParams as `sample` starts them."""
    return make_bank(layouts, 1, max(len(lay.cylinders) for lay in layouts)).rooms


@functools.partial(jax.jit, static_argnames="steps", compiler_options=XLA_CPU_CODE)
def _walk(params, robot, steps=250):
    """[T, K, C, 2] positions and velocities of the walkers of params [K] over `steps` control
    steps (250: 25 s) next to a robot standing at `robot` [2] (None: no robot), computed by
    XLA's own CPU code, which runs the long walks faster than the session's."""

    def body(p, _):
        stood = None if robot is None else (robot, jnp.zeros(2), ROBOT)
        p = jax.vmap(lambda q: motion.advance(q, DT, stood))(p)
        return p, (p.cyl_pos, p.motion.walkers.velocity)

    return jax.lax.scan(body, params, None, steps)[1]


def test_reactive_walkers_give_way_and_non_reactive_ones_do_not():
    # A person walking at 1 m/s straight at a robot standing in its way (x axis), in a room
    # wide enough to pass and in a corridor too narrow to: the reactive one sidesteps or stops
    # short, the non-reactive one walks through the robot's position.
    walk = ((2.5, 0.0), (-2.5, 0.0))
    rooms = [
        _room(_walker(*walk, reactive=True)),
        _room(_walker(*walk, reactive=False)),
        _room(_walker(*walk, reactive=True), size=(8.0, 1.0)),
    ]
    pos, vel = (np.asarray(x)[:, :, 0] for x in _walk(_params(rooms), jnp.zeros(2)))  # [T, 3, 2]
    gap = np.linalg.norm(pos, axis=-1) - 0.25 - ROBOT  # [T, 3] edge to edge
    assert gap[:, 0].min() > 0.05 and np.abs(pos[:, 0, 1]).max() > 0.3  # sidestepped
    assert pos[-1, 0, 0] == pytest.approx(-2.5, abs=0.06)  # and went on to its goal
    assert gap[:, 1].min() < -0.3 and np.abs(pos[:, 1, 1]).max() == 0.0  # straight through
    assert gap[:, 2].min() > 0.05 and pos[-1, 2, 0] > 0.4  # stopped short, waits
    assert np.linalg.norm(vel[-1, 2]) < 1e-6


def test_walkers_reach_their_goals_at_their_speeds():
    # Four people crossing an empty room, two of them through each other's lines; one goes back
    # and forth (repeat): after reaching its goal it heads back to where it started.
    people = (
        _walker((-3.0, 0.0), (3.0, 0.0), speed=1.4),
        _walker((3.0, 0.3), (-3.0, 0.3), speed=0.6, reactive=False),
        _walker((0.0, -3.0), (0.0, 3.0), speed=0.3, radius=0.2),
        _walker((-3.0, -2.0), (1.0, -2.0), speed=1.0, repeat=True),
    )
    room = _room(*people, size=(8.0, 8.0))
    pos, vel = (np.asarray(x)[:, 0] for x in _walk(_params([room]), None))  # [T, 4, 2]
    goals = np.array([p.motion.goal for p in people])
    speed = np.linalg.norm(vel, axis=-1)  # [T, 4]
    assert (speed <= np.array([1.4, 0.6, 0.3, 1.0]) + 1e-5).all()
    np.testing.assert_allclose(pos[-1, :3], goals[:3], atol=crowd.ARRIVE + 1e-3)
    there = int(np.argmax(np.linalg.norm(pos[:, 3] - goals[3], axis=-1) < crowd.ARRIVE))
    assert 35 < there < 60  # 4 m at 1 m/s
    home = np.linalg.norm(pos[there:, 3] - people[3].pos, axis=-1) < crowd.ARRIVE
    assert 40 <= np.argmax(home) < 60  # back where it started (giving way to the slow one)
    assert (speed[:40, 0] > 1.0).mean() > 0.7  # mostly at its own pace on its way (6 m)


def test_circle_crossing_layouts_load_and_the_people_cross():
    rooms = {
        k: load_layout(CROWDNAV / f"circle_crossing_{k}.json") for k in ("reactive", "nonreactive")
    }
    for kind, layouts in rooms.items():
        assert len(layouts) == 10
        for lay in layouts:
            assert (lay.robot_pos, lay.goal_pos) == ((0.0, -4.0), (0.0, 4.0))
            assert len(lay.cylinders) == 5
            for c in lay.cylinders:
                assert c.radius == 0.3 and c.motion.speed == 1.0 and not c.motion.repeat
                assert c.motion.reactive == (kind == "reactive")
                assert np.linalg.norm(c.pos) == pytest.approx(4.0, abs=0.75)
                np.testing.assert_allclose(c.motion.goal, -np.asarray(c.pos))
    # Without the robot (it neither stops nor turns them), every person reaches the opposite
    # point within CrowdNav's 25 s, giving way to the others on the way.
    layouts = rooms["reactive"]
    pos, _ = _walk(_params(layouts), None)  # [T, K, 5, 2]
    goals = np.array([[c.motion.goal for c in lay.cylinders] for lay in layouts])
    left = np.linalg.norm(np.asarray(pos) - goals, axis=-1)  # [T, K, 5]
    assert (left[-1] < 0.1).all(), left[-1]
    apart = np.asarray(pos)[:, :, :, None] - np.asarray(pos)[:, :, None]  # [T, K, 5, 5, 2]
    dist = np.linalg.norm(apart, axis=-1) + 10 * np.eye(5)
    assert dist.min() > 0.6 - 0.05  # they barely touch one another


def _crossings(rooms: int, seed: int) -> list[RoomLayout]:
    """`rooms` circle crossings of 4-8 reactive people (CrowdNav's, randomised, back and forth):
    each between a point of a 3-4.5 m circle, 0.5 m of noise per axis, and the opposite point
    at 0.5-1.4 m/s; ends 0.7 m apart from the others' (CrowdNav's rule)."""
    rng = np.random.default_rng(seed)
    layouts = []
    for i in range(rooms):
        ends, people, radius = [], [], rng.uniform(3.0, 4.5)
        for _ in range(rng.integers(4, 9)):
            while True:
                a = rng.uniform(-np.pi, np.pi)
                p = radius * np.array([np.cos(a), np.sin(a)]) + rng.uniform(-0.5, 0.5, 2)
                if all(np.linalg.norm(p - e) > 0.7 and np.linalg.norm(p + e) > 0.7 for e in ends):
                    break
            ends += [p, -p]
            speed = rng.uniform(0.5, 1.4)
            people.append(_walker(tuple(p), tuple(-p), radius=0.3, speed=speed, repeat=True))
        layouts.append(_room(*people, size=(12.0, 12.0), name=f"c{i}"))
    return layouts


@pytest.mark.slow
def test_people_meeting_from_every_side_never_stand_for_good():
    """People who meet at a circle's centre or face to face do not stand for good: nobody stands
    for others longer than the patience rule's `PATIENCE`, everyone reaches the far side, and no
    one steps into another. Slow: 640 rooms of walkers compiled and walked for 60 s for this
    check."""
    # Crowds meeting at a circle's centre, or face to face, can leave every candidate but
    # standing closing on someone. Without the patience rule 40 of the first 256 rooms' people
    # stood 5 s or more in 60 s, one for 39 s. Without the slots' order in `_apart`, two bold
    # people whose steps clash both stand, choose the same steps again, and stand until
    # something else moves: 3 people of these rooms stood 1.9-2.6 s (on a GPU's rounding, one
    # of the first 256 rooms' 2.0 s).
    layouts = _crossings(640, seed=0)
    pos, vel = (np.asarray(x) for x in _walk(_params(layouts), None, steps=600))  # [T, K, C, 2]
    n = max(len(lay.cylinders) for lay in layouts)
    here = np.arange(n) < np.array([len(lay.cylinders) for lay in layouts])[:, None]  # [K, C]
    goals = np.array([[c.motion.goal for c in lay.cylinders] + [(0, 0)] * (n - len(lay.cylinders))
                      for lay in layouts])  # fmt: skip
    there = (np.linalg.norm(pos - goals, axis=-1) < crowd.ARRIVE + 1e-3).any(0)  # [K, C]
    assert there[here].all()
    stands, longest = np.zeros(here.shape), np.zeros(here.shape)
    for speed in np.linalg.norm(vel, axis=-1):  # [K, C] a step
        stands = np.where((speed < 1e-4) & here, stands + 1, 0)
        longest = np.maximum(longest, stands)
    assert longest.max() <= round(crowd.PATIENCE / DT) + 2  # in steps
    apart = np.linalg.norm(pos[:, :, :, None] - pos[:, :, None], axis=-1)  # [T, K, C, C]
    both = here[:, :, None] & here[:, None] & ~np.eye(n, dtype=bool)
    assert apart[:, both].min() > 0.6 - 1e-3
    assert np.linalg.norm(vel, axis=-1).max() <= 1.4 + 1e-5


def test_of_two_walkers_whose_steps_clash_the_earlier_slot_steps():
    """`_apart`: a step that comes within touch of where another stands is never taken; of two
    steps that clash, the walker in the later slot stands and the earlier one steps, so the
    next step does not start from the same standstill."""
    pos = jnp.array([[0.0, 0.0], [0.8, 0.0], [3.0, 0.0], [0.0, 2.0]])  # [C, 2]
    new = jnp.array([[0.1, 0.0], [0.65, 0.0], [3.2, 0.0], [0.0, 2.1]])  # 0 and 1 clash
    radius, walking = jnp.full(4, 0.3), jnp.array([True, True, True, True])
    np.testing.assert_array_equal(crowd._apart(pos, new, radius, walking), [0, 1, 0, 0])
    # Slot order decides, not position: swapped slots, the other one steps.
    order = jnp.array([1, 0, 2, 3])
    np.testing.assert_array_equal(
        crowd._apart(pos[order], new[order], radius, walking), [0, 1, 0, 0]
    )
    # Stepping to within touch of where another stands now: stopped, the first slot too.
    np.testing.assert_array_equal(
        crowd._apart(pos, new.at[0].set([2.5, 0.0]), radius, walking), [1, 0, 0, 0]
    )
    # Whoever still steps keeps clear of everyone's new place.
    moved = jnp.where(crowd._apart(pos, new, radius, walking)[:, None], pos, new)
    gap = jnp.linalg.norm(moved[:, None] - moved[None], axis=-1) + 10 * jnp.eye(4)
    assert float(gap.min()) >= 0.6


def test_walker_motion_parsing_round_trip_and_errors():
    room = {
        "room": {"size": [6, 4]},
        "obstacles": [
            {"type": "cylinder", "pos": [-2, 1], "radius": 0.3, "motion": {"goal": [2, 1], "speed": 1.2}},
            {"type": "cylinder", "pos": [2, -1], "radius": 0.3, "motion": {"velocity": [0.3, 0]}},
        ],
    }  # fmt: skip
    layout = parse_layouts(room)[0]
    assert layout.obstacles[0].motion == Motion(goal=(2.0, 1.0), speed=1.2)
    assert layout.obstacles[0].motion.reactive and layout.obstacles[0].motion.repeat
    assert parse_layouts(layout_to_dict(layout))[0] == layout
    bad = {
        "obstacles[0].motion.speed: must be > 0 and <= 1.5": {"goal": [2, 1], "speed": 2},
        "obstacles[0].motion.speed: missing required field": {"goal": [2, 1]},
        "obstacles[0].motion.reactive: must be true or false": {
            "goal": [2, 1],
            "speed": 1,
            "reactive": "yes",
        },
        'obstacles[0].motion.repeat: only with "goal"': {"velocity": [1, 0], "repeat": False},
        "obstacles[0].motion.goal: cylinder at [3.0, 1.0] reaches 0.300 m beyond the east": {
            "goal": [3, 1],
            "speed": 1,
        },
        "obstacles[0].motion: must have either": {"goal": [2, 1], "velocity": [1, 0]},
    }
    for message, value in bad.items():
        room["obstacles"][0]["motion"] = value
        with pytest.raises(LayoutError, match="^f.json: room #0: " + re.escape(message)):
            parse_layouts(room, "f.json")
    room["obstacles"][0] = {
        "type": "box",
        "pos": [0, 0],
        "size": [1, 1],
        "motion": {"goal": [1, 1], "speed": 1},
    }
    with pytest.raises(LayoutError, match=re.escape("obstacles[0].motion.goal: only a cylinder")):
        parse_layouts(room, "f.json")


def test_walker_config_spec_and_errors():
    cfg = crowd.WalkerConfig.parse("count=2:6, speed=0.5:1.2,reactive=1")
    assert (cfg.count, cfg.speed, cfg.reactive, cfg.slots) == ((2, 6), (0.5, 1.2), 1.0, 6)
    assert crowd.WalkerConfig.parse("") == crowd.WalkerConfig()
    for spec, message in {
        "cout=2": "unknown field 'cout'",
        "count=a": "count must be numbers",
        "speed=0.5:2": "WalkerConfig.speed: need 0 < low <= high <= 1.5",
        "reactive=2": "WalkerConfig.reactive: must be in [0, 1]",
        "count=1:40": "at most 16",
    }.items():
        with pytest.raises(ValueError, match="^RandomizeConfig.walkers: .*" + re.escape(message)):
            crowd.WalkerConfig.parse(spec)


def _no_end_where_another_stays(rooms):
    """No walker of `rooms` (SceneParams [E, ...]) turns or stays (its goal, its next goal) within
    touch of where another walker stays for good: each gets where it goes, as CrowdNav's people."""
    w = jax.device_get(rooms.motion.walkers)
    walking = (w.speed > 0) & np.asarray(rooms.cyl_active)  # [E, C]
    stays = walking & (w.goal == w.back).all(-1)
    radius = np.asarray(rooms.cyl_radius)
    for ends in (w.goal, w.back):  # [E, C, 2]
        gap = np.linalg.norm(ends[:, :, None] - w.goal[:, None], axis=-1)  # [E, C, C]: i's, j's
        touch = gap < radius[:, :, None] + radius[:, None]
        other = ~np.eye(radius.shape[1], dtype=bool)
        assert not (touch & other & walking[:, :, None] & stays[:, None]).any()


@pytest.mark.slow
def test_aimed_walkers_cross_the_robots_way():
    """An aimed walker crosses as in CrowdNav's circle crossing: it starts near the circle whose
    diameter is the straight way from the spawn to the goal (or, without a goal, a circle of
    1-4 m radius centred ahead of the spawn) and walks to the point opposite across its centre,
    where it stays; the others cross the room back and forth, mostly missing the way's middle.
    Nobody's goal or turning point is where another stays. Slow: the walkers' placement compiled
    twice (half and all of them aimed) for this check."""
    lay = RoomLayout(
        name="way",
        size=(8.0, 8.0),
        robot_pos=(-3.0, 0.0),
        obstacles=(_walker((3.5, 3.5), (3.5, 3.5)),),
    )
    room = jax.tree_util.tree_map(lambda x: x[0], make_bank([lay], 1, 4).rooms)  # facing +x
    keys = jax.random.split(jax.random.PRNGKey(0), 200)

    def crossings(aimed, goal):
        """[N, 2] starts, [N, 2] ends and [N] stays of the walkers placed in slots 1-3 of 200
        draws."""
        cfg = crowd.WalkerConfig(count=(3, 3), aimed=aimed)
        add = jax.jit(jax.vmap(lambda k: crowd.add_walkers(k, room, cfg, 1, ROBOT, goal)))
        p = add(keys)
        on = np.asarray(p.cyl_active)[:, 1:]
        assert on.mean() > 0.9  # every walker finds a crossing in 16 draws, nearly always
        w = p.motion.walkers
        _no_end_where_another_stays(p)
        stays = np.asarray(w.back == w.goal).all(-1)[:, 1:][on]  # it stays at its goal
        return np.asarray(p.cyl_pos)[:, 1:][on], np.asarray(w.goal)[:, 1:][on], stays

    noise = np.hypot(crowd.AIM_NOISE, crowd.AIM_NOISE) + 1e-4
    start, end, aimed = crossings(0.5, jnp.array((3.0, 0.0)))  # the circle of radius 3 around 0
    assert 0.35 < aimed.mean() < 0.65
    np.testing.assert_allclose((start[aimed] + end[aimed]) / 2, 0.0, atol=1e-5)
    assert np.abs(np.linalg.norm(start[aimed], axis=-1) - 3.0).max() <= noise
    assert (np.linalg.norm((start + end)[~aimed] / 2, axis=-1) < 0.5).mean() < 0.2
    start, end, aimed = crossings(1.0, None)  # circles centred 1-4 m ahead: (-2..1, 0)
    via = (start + end) / 2
    assert aimed.all() and np.abs(via[:, 1]).max() < 1e-5
    assert -2 - 1e-5 <= via[:, 0].min() <= via[:, 0].max() <= 1
    assert np.abs(np.linalg.norm(start - via, axis=-1) - (via[:, 0] + 3)).max() <= noise
    with pytest.raises(ValueError, match="WalkerConfig.aimed: must be in"):
        crowd.WalkerConfig(aimed=1.5)


# ------------------------------------------------------------------------------
# In the env: the sampler's walkers, the attribution of collisions, no recompiling

STAND = (_walker((2.5, 0.0), (-2.5, 0.0), reactive=False), _walker((2.5, 0.0), (-2.5, 0.0)))
ROOMS = [
    _room(STAND[0], name="non-reactive comes"),  # 0: runs into the standing robot
    _room(STAND[1], name="reactive comes"),  # 1: gives way
    _room(_walker((1.2, 0.0), (1.2, 0.0), reactive=False), name="robot drives"),  # 2: waits
]


@pytest.fixture(scope="module")
def crowd_run():
    """`avoid` (continuous actions, exact physics) in ROOMS and, half the episodes, sampled rooms
    of the `crowd` family: 64 episodes reset twice (other keys) and stepped 40 times, the robot
    standing except in 'robot drives' (forward at 0.5 m/s). Returns the env, the first batch's
    reset params and, per step, collision, walker_hit and done [40, 64] and the sampled walkers'
    speeds [40, 64, C]."""
    cfg = dataclasses.replace(EXACT, sampled_room_prob=0.5, families="crowd")
    env = jaxnav.make_env(
        "avoid", layouts=ROOMS, randomize=cfg, actions="continuous", sensor=SensorConfig(rows=1)
    )
    reset, step = traced_once(env)
    reset_b, step_b = jax.jit(jax.vmap(reset)), jax.jit(jax.vmap(step))
    for seed in (1, 0):  # new rooms and walkers: nothing is traced again
        states = reset_b(jax.random.split(jax.random.PRNGKey(seed), 64))
    start = jax.device_get(states.info["params"])
    drives = np.asarray(start.layout_id) == 2
    actions = jnp.where(jnp.asarray(drives)[:, None], jnp.array([0.5, 0.0]), 0.0)
    out = []
    for _ in range(40):
        states = step_b(states, actions)
        m, w = states.metrics, states.info["params"].motion.walkers
        out.append(
            (m["collision"], m["walker_hit"], states.done, jnp.linalg.norm(w.velocity, axis=-1))
        )
    return env, start, [np.asarray(x) for x in zip(*out, strict=True)]


@pytest.mark.slow
def test_env_declares_the_walker_metrics(crowd_run):
    """The env declares walker_hit, and evaluation the collisions the robot caused. Slow: the
    walker env compiles and rolls out 40 steps of 64 episodes for these tests."""
    env, _, _ = crowd_run
    assert env.metric_names == ("collision", "walker_hit")
    assert [m.name for m in env.eval_metrics][-2:] == [
        "robot_collision_rate",
        "collision_free_unhit_rate",
    ]
    assert env.walkers.slots == env.walkers.crowd_count[1] == 6


@pytest.mark.slow
def test_sampled_walkers_start_clear_at_their_speeds(crowd_run):
    """Sampled walkers start clear of everything, at speeds in their range. Slow: the walker env
    compiles and rolls out 40 steps of 64 episodes for these tests."""
    env, p, (_, _, _, speed) = crowd_run
    crowd_rooms = np.asarray(p.layout_id) == crowd.CROWD_ROOM  # [E]
    assert 20 < crowd_rooms.sum() < 44
    w = p.motion.walkers
    walks = np.asarray(w.speed > 0) & np.asarray(p.cyl_active)  # [E, C]
    count = walks.sum(-1)
    assert (
        count[~crowd_rooms] == [len(ROOMS[i].cylinders) for i in p.layout_id[~crowd_rooms]]
    ).all()
    assert count[crowd_rooms].max() <= 6 and np.mean(count[crowd_rooms]) > 3
    sampled = walks & crowd_rooms[:, None]
    r, v = np.asarray(p.cyl_radius)[sampled], np.asarray(w.speed)[sampled]
    assert r.min() >= 0.2 - 1e-6 and r.max() <= 0.3 + 1e-6
    assert v.min() >= 0.3 - 1e-6 and v.max() <= 1.4 + 1e-6
    assert 0.25 < np.asarray(w.reactive)[sampled].mean() < 0.75
    # Clear of the still obstacles and walls, and of the robot by the clearance.
    still = p.replace(cyl_active=p.cyl_active & ~walks)
    clear = np.asarray(jax.vmap(signed_distance)(still, p.cyl_pos))  # [E, C]
    assert (clear[sampled] > np.asarray(p.cyl_radius)[sampled]).all()
    gap = np.linalg.norm(np.asarray(p.cyl_pos) - np.asarray(p.spawn)[:, None, :2], axis=-1)
    gap -= np.asarray(p.cyl_radius) + env.robot.radius
    assert gap[sampled].min() >= crowd.WalkerConfig().clearance
    # Their goals across the room; walking no faster than their own pace.
    goal, start = np.asarray(w.goal)[sampled], np.asarray(p.cyl_pos)[sampled]
    assert np.linalg.norm(goal - start, axis=-1).min() > 0.6 * 5.0 - 1.0
    pace = np.broadcast_to(np.asarray(w.speed), speed.shape)
    assert (speed <= pace + 1e-5).all() and (speed[:, sampled] > 0).mean() > 0.8


@pytest.mark.slow
def test_collisions_are_attributed(crowd_run):
    """A non-reactive walker hitting a robot that stood is told apart from the robot's
    collisions. Slow: the walker env compiles and rolls out 40 steps of 64 episodes for these
    tests."""
    _, p, (collision, walker_hit, done, _) = crowd_run
    ids = np.asarray(p.layout_id)
    first = np.argmax(done, axis=0)  # [E] the step each episode ended (0: still running)
    ended = done.any(0)
    at_end = lambda x: x[first, np.arange(x.shape[1])]  # noqa: E731
    hit, by_walker = at_end(collision), at_end(walker_hit)
    comes, yields, drives = (ids == 0), (ids == 1), (ids == 2)
    assert comes.any() and yields.any() and drives.any()
    assert (ended & (hit == 1) & (by_walker == 1))[comes].all()  # the walker's doing
    assert not ended[yields].any()  # it gave way: no contact in 4 s
    assert (ended & (hit == 1) & (by_walker == 0))[drives].all()  # the robot's doing
    assert (walker_hit <= collision).all()


def test_walker_metrics_count_what_the_robot_caused():
    """Four episodes: a walker ran into the standing robot (0), the robot collided (2), two
    reached the goal (1, 3). Robot-caused: 1 of 4; of the three nobody ran into, 2 collision-free
    and 2 successes. Where a walker ran into it in every episode, the share reads 0."""
    room = {
        "collided": np.array([True, False, True, False]),
        "metrics": {"walker_hit": np.array([1.0, 0, 0, 0]), "success": np.array([0, 1.0, 0, 1])},
    }
    declared = declared_values((*WALKER_EVAL_METRICS, success_unhit("success")), room)
    got = {name: pooled(*both) for name, both in declared.items()}
    assert got == pytest.approx(
        {
            "robot_collision_rate": 0.25,
            "collision_free_unhit_rate": 2 / 3,
            "success_unhit_rate": 2 / 3,
        }
    )
    hit = {
        "collided": np.ones(4, bool),
        "metrics": {"walker_hit": np.ones(4), "success": np.zeros(4)},
    }
    values, over = declared_values(WALKER_EVAL_METRICS, hit)["collision_free_unhit_rate"]
    assert not over.any() and pooled(values, over) == 0.0  # none to judge: every one collided


def test_pictures_draw_the_walkers_and_replays_give_way():
    from matplotlib.figure import Figure

    from jaxnav.viz.plots import draw_movers
    from jaxnav.viz.render import _moving_rooms

    params = jax.tree_util.tree_map(lambda x: x[0], _params([ROOMS[1]]))  # a reactive walker
    ax = Figure().add_subplot()
    assert draw_movers(ax, params)
    assert len(ax.patches) == 1 and len(ax.lines) == 1  # its outline and its line to its goal
    # A video's replay has the walker give way to the robot where the episode had it.
    rooms = _moving_rooms(params, np.zeros((60, 3)), DT, ROBOT)
    gap = np.linalg.norm(np.asarray(rooms.cyl_pos)[:, 0], axis=-1) - 0.25 - ROBOT
    assert gap.min() > 0.05 and np.asarray(rooms.cyl_pos)[-1, 0, 0] < 0.0


@pytest.mark.slow
def test_goal_task_among_people():
    """The goal task in `crowd` rooms with walkers in every room too: they start off the goal's
    disc, the metrics name `walker_hit`, and new people never recompile. Slow: it compiles a
    goal env of its own (over a minute on 2 cores)."""
    cfg = dataclasses.replace(EXACT, families="crowd", walkers="count=1:2")
    env = jaxnav.make_env("goal", layouts=[], randomize=cfg, sensor=SensorConfig(rows=1))
    assert env.metric_names == ("collision", "success", "path_length", "walker_hit")
    reset, step = traced_once(env)
    reset_b, step_b = jax.jit(jax.vmap(reset)), jax.jit(jax.vmap(step))
    for seed in (0, 1):
        states = reset_b(jax.random.split(jax.random.PRNGKey(seed), 32))
        p = jax.device_get(states.info["params"])
        walks = np.asarray(p.motion.walkers.speed > 0) & np.asarray(p.cyl_active)
        goal = np.asarray(states.info["goal"])[:, None]
        off = np.linalg.norm(np.asarray(p.cyl_pos) - goal, axis=-1) - np.asarray(p.cyl_radius)
        assert walks.sum(-1).min() >= 1 and off[walks].min() > env.robot.radius
        for _ in range(2):
            states = step_b(states, jnp.zeros(32, jnp.int32))
    assert set(states.metrics) == set(env.metric_names)


@pytest.mark.slow
def test_foresight_plans_wait_for_a_person_who_does_not_give_way():
    """benchmarks/crowdnav_foresight.py in a room of one non-reactive person who crosses the
    robot's straight way at 1 m/s just as a robot driving at once (0.5 m/s) gets there: the plan
    that drives at once collides, the one that stands 4 s first reaches the goal, and a detour
    that passes behind the person's start does too; the tallies read the same runs. Slow: it
    compiles the goal env's 250-step scan (about 7 s on 2 cores)."""
    from jaxnav.tasks.goal import GoalConfig

    module = benchmark_script("crowdnav_foresight")
    crosser = _walker((-3.0, -1.5), (3.5, -1.5), reactive=False, speed=1.0)
    room = RoomLayout(
        name="cross",
        size=(8.0, 8.0),
        robot_pos=(0.0, -3.0),
        robot_yaw=float(np.pi / 2),
        obstacles=(crosser,),
        goal_pos=(0.0, 3.0),
    )
    task = GoalConfig(actions="continuous", max_steps=module.STEPS)
    randomize = eval_randomize("layout", False)
    env = jaxnav.make_env("goal", layouts=[room], task=task, randomize=randomize)
    waits = np.array([0.0, 4.0, 0.0])
    points = np.array([[np.nan, np.nan], [np.nan, np.nan], [-3.5, -2.5]])
    run = module.make_run(env, waits, points)
    success, collision, walker_hit = (np.asarray(x) for x in run(jax.random.PRNGKey(0)))
    assert collision.tolist() == [True, False, False] and not walker_hit.any()
    assert success.tolist() == [False, True, True]
    (row,) = module.room_rows(success, collision, walker_hit, waits, points, ["cross"])
    assert row["solved"] and row["least_wait_s"] == 0.0 and row["straight_wait_s"] == 4.0
    assert module.summary([row])["straight_waits_ok_everywhere"] == [4.0]
