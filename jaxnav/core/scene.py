"""Rooms on MuJoCo MJX: one model with fixed obstacle slots, per-env geometry in batched fields.

Every env of a batch shares one `mjx.Model` structure (geom types and collision pairs are static),
while the geometry that differs between rooms (wall positions, obstacle poses and sizes) lives in the
`geom_pos`, `geom_quat` and `geom_size` fields, rebuilt from each env's `SceneParams`. Unused slots are
parked under the floor, where neither the robot nor the depth rays can reach them.

Two physics models of the robot (`SceneConfig.physics`): "fast", the base pushed along the floor by
forces that track the command (`RobotSpec.mjcf`, one 0.1 s step per control step), and "wheeled",
the validation model: the base on two driven wheels and castors with gravity and friction contacts
(`RobotSpec.wheeled_mjcf`, its own timestep and solver). In both, qpos[:3] is the base's pose
(x, y, yaw): the sensor, collision detection and evaluation read only that. By default (MJX's
contacts skipped, `SceneConfig.fast_contacts`) the fast physics steps a model of the robot alone
(`build_robot_model`); the room model serves the contacts, the wheeled physics and rendering.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from jaxnav.core import mjx
from jaxnav.core.assets import scenes_dir
from jaxnav.core.checks import require_finite
from jaxnav.core.robot import TURTLEBOT2I, RobotSpec

SCENES_DIR = scenes_dir()

OBSTACLE_GROUP = 1  # geom group of walls and obstacles: the only geoms the depth rays see
FLOOR_AFFINITY = 2  # the floor's conaffinity: robot geoms of contype 2 (wheels, castors) touch it
PHYSICS = ("fast", "wheeled")
WHEELS = ("wheel_left", "wheel_right")  # the wheeled model's wheel joints, geoms and actuators
PARK_DEPTH = -10.0  # m; z of parked slots, far below the floor and the rays
# The MJX stages the fast physics skips without `fast_contacts`: collision, the constraint solver.
_NO_CONTACTS = mujoco.mjtDisableBit.mjDSBL_CONTACT | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
_WALL_NORMALS = np.array([[-1, 0], [1, 0], [0, -1], [0, 1]], np.float64)  # east, west, north, south


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Static structure of the simulated room; changing it recompiles."""

    physics: str = "fast"
    """The robot's physics: 'fast' (forces on a planar base that track the command, within the
    floor's traction) or 'wheeled' (the validation model: two driven wheels, castors, gravity and
    friction contacts, `RobotSpec.wheeled_mjcf`; its MJCF sets its own timestep and solver, and
    it runs control_period / timestep steps per control step)."""
    num_boxes: int = 8
    """Box obstacle slots per room."""
    num_cylinders: int = 4
    """Cylinder obstacle slots per room (capsules standing through the floor, see `build_mj_model`)."""
    timestep: float = 0.1
    """Physics timestep in seconds; `substeps * timestep` is the control period (both physics).
    One 0.1 s step moves the robot at most 7 cm, well under its 17.7 cm radius, so it cannot
    tunnel (tested)."""
    substeps: int = 1
    """Physics steps per control step of the fast physics (measured: 1 x 0.1 s is 1.6x faster
    than 2 x 0.05 s)."""
    solver_iterations: int = 1
    """Constraint solver iterations of the fast physics; a contact ends the episode, so one Newton
    step suffices."""
    fast_contacts: bool = False
    """Run MJX's contact pass and constraint solver in the fast physics (True: the full MJX path).
    Off (default), MJX skips both and steps the robot alone (`build_robot_model`): a contact
    only ever ends the episode, which the analytic collision test (`NavTask.touching`) does at
    the first touch, and MuJoCo applies contact forces only from a pose that already penetrates,
    never the start of a step of a live episode. So episodes are bit-identical to the full path
    with one substep, the colliding step included (tested); with more, the rest of the colliding
    step goes on into the obstacle. The wheeled physics always runs them (its wheels roll on
    floor contacts)."""

    def __post_init__(self):
        if self.physics not in PHYSICS:
            raise ValueError(
                f"SceneConfig.physics: must be one of {', '.join(PHYSICS)}, got {self.physics!r}"
            )
        for name in ("num_boxes", "num_cylinders"):
            if getattr(self, name) < 0:
                raise ValueError(f"SceneConfig.{name}: must be >= 0, got {getattr(self, name)}")
        require_finite(self)
        if self.timestep <= 0:
            raise ValueError(f"SceneConfig.timestep: must be > 0 s, got {self.timestep}")
        for name in ("substeps", "solver_iterations"):
            if getattr(self, name) < 1:
                raise ValueError(f"SceneConfig.{name}: must be >= 1, got {getattr(self, name)}")

    @property
    def control_period(self) -> float:
        return self.timestep * self.substeps


def yaw_quat(yaw):
    """[..., 4] MuJoCo (w, x, y, z) quaternion of a rotation by `yaw` about z."""
    half = 0.5 * jnp.asarray(yaw)
    zero = jnp.zeros_like(half)
    return jnp.stack([jnp.cos(half), zero, zero, jnp.sin(half)], axis=-1)


def _z_to(normal: np.ndarray) -> list[float]:
    """Quaternion turning +z onto a horizontal unit `normal` (a quarter turn about z x normal)."""
    axis = np.array([-normal[1], normal[0], 0.0])
    return [np.sqrt(0.5), *(np.sqrt(0.5) * axis)]


def mjcf_field(physics: str) -> str:
    """The `RobotSpec` field naming the MJCF of `physics`."""
    return "mjcf" if physics == "fast" else "wheeled_mjcf"


def robot_mjcf(robot: RobotSpec, physics: str = "fast") -> Path:
    """The robot's MJCF file of `physics` (`RobotSpec.mjcf` or `.wheeled_mjcf`): a path, or a
    file name among jaxnav's scenes."""
    field = mjcf_field(physics)
    name = getattr(robot, field)
    path = Path(name)
    if not path.is_absolute() and not path.exists():
        path = SCENES_DIR / name
    if not path.is_file():
        raise ValueError(f"RobotSpec.{field}: no such file: {name}")
    return path


def _mjcf_source(robot: RobotSpec, physics: str) -> str:
    """'RobotSpec.<field>: <file>': the robot's MJCF of `physics`, as error messages name it."""
    field = mjcf_field(physics)
    return f"RobotSpec.{field}: {getattr(robot, field)}"


def _mjcf_error(cfg: SceneConfig, robot: RobotSpec, problem: str) -> ValueError:
    """One line naming the robot's MJCF field and file, for what MuJoCo said of it."""
    return ValueError(f"{_mjcf_source(robot, cfg.physics)}: {' '.join(problem.split())}")


def _robot_spec(cfg: SceneConfig, robot: RobotSpec) -> mujoco.MjSpec:
    """The robot's MJCF of `cfg.physics` as a spec; the fast physics with `cfg`'s timestep and
    solver iterations (and on a GPU a sparse mass matrix), the wheeled model with its MJCF's own
    options."""
    try:
        spec = mujoco.MjSpec.from_file(str(robot_mjcf(robot, cfg.physics)))
    except ValueError as err:  # MuJoCo's parser: a malformed file
        raise _mjcf_error(cfg, robot, str(err)) from None
    if cfg.physics == "fast":
        spec.option.timestep = cfg.timestep
        spec.option.iterations = cfg.solver_iterations
        spec.option.ls_iterations = cfg.solver_iterations
        if not cfg.fast_contacts:
            spec.option.disableflags |= _NO_CONTACTS
        if jax.default_backend() == "gpu":
            # The base's three joints: MJX factors M densely (below 60 degrees of freedom, but on
            # a TPU), on a GPU a batched Cholesky call and two triangular solves a step; its
            # sparse factorisation is a few element-wise ops that fuse. On the CPU the sparse one
            # stepped no faster (docs/results.md, "What was decided and why").
            spec.option.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
    return spec


def _compiled(
    spec: mujoco.MjSpec, cfg: SceneConfig, robot: RobotSpec, why: str = ""
) -> mujoco.MjModel:
    """`spec` compiled, with MuJoCo's Euler damping off where it would add nothing; a compiler
    error names the robot's MJCF (and ends with `why`)."""
    try:
        m = spec.compile()
    except ValueError as err:
        raise _mjcf_error(cfg, robot, f"{err}{why}") from None
    if m.opt.disableflags & _NO_CONTACTS and not m.dof_damping.any():
        # Euler's implicit damping would refactor M to add nothing (MuJoCo itself skips it then).
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    return m


def build_robot_model(cfg: SceneConfig, robot: RobotSpec = TURTLEBOT2I) -> mujoco.MjModel:
    """The robot's bodies, joints and actuators alone, with `build_mj_model`'s options: what the
    fast physics without MJX contacts steps (`Scene.physics_model`). There nothing acts on the
    robot but its motors, and nothing reads more than `qpos` and `qvel`: the room's geoms and the
    robot's own (its shapes, sites, camera, sensors, contact pairs) would only add work to every
    step. Each body keeps its mass and inertia as the whole MJCF has them (geoms may give them),
    so the dynamics are the full model's."""
    spec = _robot_spec(cfg, robot)
    whole = _compiled(spec, cfg, robot)
    for body in spec.bodies[1:]:  # the world body has no inertia of its own
        i = body.id  # its index in `whole`
        body.mass, body.inertia = whole.body_mass[i], whole.body_inertia[i]
        body.ipos, body.iquat = whole.body_ipos[i], whole.body_iquat[i]
        body.explicitinertial = True
    for kind in ("sensors", "pairs", "excludes", "geoms", "sites", "cameras", "lights"):
        for element in list(getattr(spec, kind)):
            spec.delete(element)
    # E.g. an actuator or a tendon on a site cannot do without it:
    alone = "; so the robot without its geoms and sites does not compile: run its physics with "
    alone += "MJX's contacts (--scene.fast-contacts true), which steps the whole model"
    return _compiled(spec, cfg, robot, alone)


def build_mj_model(cfg: SceneConfig, robot: RobotSpec = TURTLEBOT2I) -> mujoco.MjModel:
    """Robot MJCF + floor + 4 plane walls + obstacle slots (boxes, then cylinders), all parked.

    Cylinders are capsules whose round part spans z in [0, height]: MJX has no cylinder ray and no
    cylinder-box collision, while capsules have both, and below the robot's and camera's heights the two
    shapes are identical. The fast physics takes its timestep and solver iterations from `cfg`; the
    wheeled model keeps its MJCF's own.
    """
    spec = _robot_spec(cfg, robot)
    spec.add_material(name="floor", rgba=[0.85, 0.85, 0.8, 1])
    spec.add_material(name="wall", rgba=[0.7, 0.6, 0.5, 1])
    spec.add_material(name="obstacle", rgba=[0.3, 0.5, 0.8, 1])
    world = spec.worldbody
    world.add_light(pos=[0, 0, 6], dir=[0, 0, -1])
    world.add_geom(
        name="floor",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        size=[0, 0, 0.05],
        material="floor",
        group=2,
        contype=0,
        conaffinity=FLOOR_AFFINITY,
    )
    solid = dict(contype=0, conaffinity=1, condim=1, group=OBSTACLE_GROUP)
    for i, normal in enumerate(_WALL_NORMALS):
        world.add_geom(
            name=f"wall{i}",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0, 0, 0.05],
            pos=[-normal[0] * 3, -normal[1] * 3, 0],
            quat=_z_to(normal),
            material="wall",
            **solid,
        )
    for i in range(cfg.num_boxes):
        world.add_geom(
            name=f"box{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.1, 0.1, 0.1],
            pos=[0, 0, PARK_DEPTH],
            material="obstacle",
            **solid,
        )
    for i in range(cfg.num_cylinders):
        world.add_geom(
            name=f"cylinder{i}",
            type=mujoco.mjtGeom.mjGEOM_CAPSULE,
            size=[0.1, 0.1, 0],
            pos=[0, 0, PARK_DEPTH],
            material="obstacle",
            **solid,
        )
    return _compiled(spec, cfg, robot)


def _bumper_span(m: mujoco.MjModel, bumper: int, source: str) -> tuple[tuple[float, float], float]:
    """((low, high) heights of its axis, radius) of the collision geom `bumper`: a sphere, or a
    capsule standing upright, on the base's axis (what geometry.signed_distance tests)."""
    kind, pos, size = m.geom_type[bumper], m.geom_pos[bumper], m.geom_size[bumper]
    upright = np.allclose(np.abs(m.geom_quat[bumper]), [1, 0, 0, 0], atol=1e-6)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        half = 0.0
    elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE and upright:
        half = float(size[1])
    else:
        half = None
    if half is None or np.abs(pos[:2]).max() > 1e-9:
        raise ValueError(
            f"{source}: geom 'bumper' must be a sphere or an upright capsule on the base's axis"
        )
    return (float(pos[2]) - half, float(pos[2]) + half), float(size[0])


def _check_pose_joints(m: mujoco.MjModel, body: int, source: str) -> None:
    """Body `base` must start with slides along x and y and a hinge about z, so that qpos[:3] is
    its pose (x, y, yaw), whatever joints follow."""
    first, count = int(m.body_jntadr[body]), int(m.body_jntnum[body])
    slide, hinge = mujoco.mjtJoint.mjJNT_SLIDE, mujoco.mjtJoint.mjJNT_HINGE
    want = ((slide, (1, 0, 0)), (slide, (0, 1, 0)), (hinge, (0, 0, 1)))
    ok = count >= 3 and all(
        m.jnt_type[first + i] == kind
        and np.allclose(m.jnt_axis[first + i], axis)
        and m.jnt_qposadr[first + i] == i
        for i, (kind, axis) in enumerate(want)
    )
    if not ok:
        raise ValueError(
            f"{source}: body 'base' must start with a slide along x, a slide "
            "along y and a hinge about z (qpos[:3] = x, y, yaw)"
        )


def _physics_substeps(cfg: SceneConfig, timestep: float, source: str) -> int:
    """Physics steps of `timestep` per control period; the wheeled model's must divide it."""
    if cfg.physics == "fast":
        return cfg.substeps
    steps = round(cfg.control_period / timestep)
    if steps < 1 or abs(steps * timestep - cfg.control_period) > 1e-9:
        raise ValueError(
            f"SceneConfig.physics: the timestep of {source} ({timestep} s) does not divide the "
            f"control period {cfg.control_period} s (SceneConfig.timestep x substeps)"
        )
    return steps


def _wheel_radius(m: mujoco.MjModel, robot: RobotSpec, source: str) -> float:
    """The radius of the wheeled model's wheels (geoms `WHEELS`), checked against the robot's
    wheelbase (what `NavTask.actuate` splits the command with) and the actuators' presence."""
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, w) for w in WHEELS]
    acts = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, w) for w in WHEELS]
    if min(ids + acts) < 0:
        raise ValueError(f"{source}: needs geoms and actuators named {', '.join(WHEELS)}")
    radius = m.geom_size[ids, 0]
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    apart = float(np.linalg.norm(d.geom_xpos[ids[0]] - d.geom_xpos[ids[1]]))
    if abs(apart - robot.wheelbase) > 1e-6 or abs(radius[0] - radius[1]) > 1e-9:
        raise ValueError(
            f"RobotSpec.wheelbase: {robot.wheelbase} m, but the wheels of {source} are "
            f"{apart:.4f} m apart (radii {radius[0]}, {radius[1]})"
        )
    return float(radius[0])


class Scene:
    """The compiled room model, the map from `SceneParams` to per-env `mjx.Model` fields, and the
    model the physics steps (`physics_model`)."""

    def __init__(self, cfg: SceneConfig = SceneConfig(), robot: RobotSpec = TURTLEBOT2I):
        self.cfg, self.robot = cfg, robot
        self.mj_model = build_mj_model(cfg, robot)
        source = _mjcf_source(robot, cfg.physics)  # for error messages
        # On this process's first device: MJX's default, jax.devices()[0], belongs to process 0
        # in a run of several processes.
        self.model = mjx.put_model(self.mj_model, device=jax.local_devices()[0])
        name = lambda n: mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_GEOM, n)  # noqa: E731
        self.wall_ids = np.array([name(f"wall{i}") for i in range(4)])
        self.box_ids = np.array([name(f"box{i}") for i in range(cfg.num_boxes)], dtype=int)
        self.cyl_ids = np.array([name(f"cylinder{i}") for i in range(cfg.num_cylinders)], dtype=int)
        # [ngeom] obstacle slot of each geom (boxes, then cylinders, as in SceneParams); -1 others.
        self.slot_of_geom = np.full(self.mj_model.ngeom, -1)
        self.slot_of_geom[np.concatenate([self.box_ids, self.cyl_ids]).astype(int)] = np.arange(
            cfg.num_boxes + cfg.num_cylinders
        )
        self.robot_body = mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_BODY, "base")
        self.bumper = name("bumper")
        # The bumper sphere's centre height and radius: what collision detection tests (see
        # geometry.signed_distance); the MJCF places it on the base's axis.
        self.bumper_z, self.bumper_radius = _bumper_span(self.mj_model, self.bumper, source)
        _check_pose_joints(self.mj_model, self.robot_body, source)
        self.mass = float(self.mj_model.body_mass[self.robot_body])
        self.yaw_inertia = float(self.mj_model.body_inertia[self.robot_body, 2])
        self.wheeled = cfg.physics == "wheeled"
        self.shared = not (self.wheeled or cfg.fast_contacts)  # one model for every env
        # What the physics steps: the robot alone where the room's geoms act on nothing (the
        # model of its `mjx.Data`), else the room model (with each env's geometry).
        self.data_model = (
            mjx.put_model(build_robot_model(cfg, robot), device=jax.local_devices()[0])
            if self.shared
            else self.model
        )
        self.timestep = float(self.mj_model.opt.timestep)  # s per physics step
        self.substeps = _physics_substeps(cfg, self.timestep, source)  # physics steps per control
        self.floor = name("floor")
        if self.wheeled:
            self.wheel_radius = _wheel_radius(self.mj_model, robot, source)
            self.wheel_actuators = np.array(
                [mujoco.mj_name2id(self.mj_model, mujoco.mjtObj.mjOBJ_ACTUATOR, w) for w in WHEELS]
            )

    def geom_fields(self, params) -> dict[str, jax.Array]:
        """One env's `geom_pos` [G, 3], `geom_quat` [G, 4] and `geom_size` [G, 3] from its params,
        and under the wheeled physics `geom_friction` [G, 3] (the floor's traction)."""
        pos = jnp.asarray(self.model.geom_pos)
        quat = jnp.asarray(self.model.geom_quat)
        size = jnp.asarray(self.model.geom_size)
        walls = -jnp.asarray(_WALL_NORMALS) * params.room_half  # [4, 2]: each wall's point
        pos = pos.at[self.wall_ids, :2].set(walls)
        if self.cfg.num_boxes:
            half_h = 0.5 * (params.box_height - params.box_bottom)  # [Sb]
            z = jnp.where(params.box_active, params.box_bottom + half_h, PARK_DEPTH)
            pos = pos.at[self.box_ids].set(jnp.column_stack([params.box_pos, z]))
            quat = quat.at[self.box_ids].set(yaw_quat(params.box_yaw))
            size = size.at[self.box_ids].set(jnp.column_stack([params.box_half, half_h]))
        if self.cfg.num_cylinders:
            half_h = 0.5 * (params.cyl_height - params.cyl_bottom)  # [Sc]
            z = jnp.where(params.cyl_active, params.cyl_bottom + half_h, PARK_DEPTH)
            pos = pos.at[self.cyl_ids].set(jnp.column_stack([params.cyl_pos, z]))
            radius = params.cyl_radius
            size = size.at[self.cyl_ids].set(
                jnp.column_stack([radius, half_h, jnp.zeros_like(radius)])
            )
        fields = {"geom_pos": pos, "geom_quat": quat, "geom_size": size}
        if self.wheeled:
            # The episode's floor traction; a contact takes the larger friction of its two geoms,
            # and the tyres' is 0, so the floor's is the wheels' (the fast drive bounds its force
            # with the same coefficient).
            friction = jnp.asarray(self.model.geom_friction)
            fields["geom_friction"] = friction.at[self.floor, 0].set(params.friction)
        return fields

    def model_for(self, params) -> mjx.Model:
        """The `mjx.Model` of one env (use under `jax.vmap` for a batch)."""
        return self.model.replace(**self.geom_fields(params))

    def physics_model(self, params) -> mjx.Model:
        """The model the physics steps one env with: its own (`model_for`), or without MJX's
        contacts (`SceneConfig.fast_contacts` off) the robot alone (`build_robot_model`), one
        for every env, since then nothing the robot does depends on the room's geoms. Its
        joints, and so `qpos` and `qvel`, are the room model's."""
        return self.data_model if self.shared else self.model_for(params)

    def batched_model(self, params) -> tuple[mjx.Model, mjx.Model]:
        """A batch's model with leading-axis geom fields, and the `in_axes` tree to vmap it with."""
        fields = jax.vmap(self.geom_fields)(params)
        in_axes = jax.tree_util.tree_map(lambda _: None, self.model)
        return self.model.replace(**fields), in_axes.replace(**{k: 0 for k in fields})
