"""Videos of episodes: MuJoCo's renderer over one env's scene, written as an animated GIF.

`render_episode` copies an episode's room into the scene's `mj_model` (`episode_model`: the same
`geom_pos`, `geom_quat` and `geom_size` the MJX model gets from `Scene.geom_fields`; the rendered
depth test draws depth images of it too), poses the robot at each recorded `qpos` and renders two
cameras side by side: a top-down free camera over the room (with the robot's path so far and its
heading) and the robot's own `depth` camera (what the Orbbec Astra sees, in colour). Moving
obstacles are replayed from the reset's `SceneParams` (`motion.advance`, deterministic), one
control step per frame.

Rendering without a display needs an OpenGL backend: EGL (Debian/Ubuntu: libegl1 and
libgl1-mesa-dri for software rendering, or the NVIDIA driver) or OSMesa (libosmesa6). mujoco picks
its backend from MUJOCO_GL when `mujoco.rendering.classic.gl_context` (in mujoco 3.x
`mujoco.gl_context`) is imported, and `import mujoco` imports it, so setting MUJOCO_GL later does
nothing by itself; `gl_backend` finds a working backend and re-imports that module with it.
"""

from __future__ import annotations

import copy
import importlib
import os
import subprocess
import sys
from pathlib import Path

import jax
import mujoco
import numpy as np

from jaxnav.core import motion
from jaxnav.viz.plots import room_shapes

GL_BACKENDS = ("egl", "osmesa")  # tried in this order when MUJOCO_GL is not set
GL_HINT = "install libegl1 or libosmesa6"
MARGIN = 0.4  # m of floor shown around the walls in the top-down view
WALL_RGBA = (0.45, 0.38, 0.32, 1.0)
TRAIL_COLOR = (0.85, 0.2, 0.1, 1.0)
ROBOT_COLOR = (1.0, 0.6, 0.0, 1.0)
HEADING_COLOR = (0.1, 0.1, 0.1, 1.0)
FOV_COLOR = (0.2, 0.6, 1.0, 0.8)
FOV_LENGTH = 1.2  # m, drawn length of the camera's field-of-view edges
WALL_GROUP = 5  # geom group of the plane walls in `episode_model`: not drawn by default

# Creates a tiny renderer and draws one frame: run in a fresh interpreter per backend.
_PROBE = """
import mujoco
m = mujoco.MjModel.from_xml_string("<mujoco><worldbody><light/><geom size='.1'/></worldbody></mujoco>")
with mujoco.Renderer(m, 16, 16) as r:
    r.update_scene(mujoco.MjData(m))
    r.render()
"""
_ARROW = mujoco.mjtGeom.mjGEOM_ARROW
_UNSET = object()
_backend = _UNSET  # gl_backend's answer, found once per process


class NoGLError(RuntimeError):
    """No OpenGL backend can render here."""


def gl_backend() -> str | None:
    """The OpenGL backend `mujoco.Renderer` uses in this process ('egl', 'osmesa', or MUJOCO_GL's
    value if set), or None if none can render here.

    Each candidate is tried in a fresh interpreter: PyOpenGL binds its platform on first import, so a
    failed EGL attempt in this process would rule out OSMesa, and a broken driver may even crash.
    """
    global _backend
    if _backend is _UNSET:
        wanted = os.environ.get("MUJOCO_GL", "").strip().lower()
        found = next((b for b in ((wanted,) if wanted else GL_BACKENDS) if _probe(b)), None)
        _backend = found if found is not None and _activate(found) else None
    return _backend


def _probe(backend: str) -> bool:
    env = {**os.environ, "MUJOCO_GL": backend}
    try:
        proc = subprocess.run(
            [sys.executable, "-c", _PROBE], env=env, capture_output=True, timeout=120
        )
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.returncode == 0


def _activate(backend: str) -> bool:
    """Makes `mujoco.Renderer` use `backend` from now on; False if that cannot be done here."""
    gl_context = importlib.import_module(mujoco.Renderer.__module__).gl_context
    if getattr(gl_context, "_MUJOCO_GL", None) == backend:
        return True
    os.environ["MUJOCO_GL"] = backend
    try:
        importlib.reload(gl_context)  # reads MUJOCO_GL again and imports that backend's GLContext
    except (ImportError, RuntimeError):
        return False
    return True


def render_episode(
    env,
    params,
    qpos_seq,
    path: str | os.PathLike,
    width: int = 480,
    height: int = 360,
    fps: int = 10,
    *,
    robot_view: bool = True,
    wall_height: float = 0.5,
    title: str | None = None,
) -> Path:
    """Writes an animated GIF of one episode and returns its path.

    `params` is the episode's SceneParams at its reset (one env's, no batch axis; its moving
    obstacles are advanced one control step per frame), `qpos_seq` [T, 3] its robot poses (x, y
    m; yaw rad), one frame each.
    Frames are the top-down view, `width` x `height` pixels, and with `robot_view` the robot's
    `depth` camera at the same size to its right. Raises NoGLError without an OpenGL backend.
    """
    qpos = np.asarray(qpos_seq, np.float64)
    if qpos.ndim != 2 or qpos.shape[1] != 3 or len(qpos) == 0:
        raise ValueError(f"qpos_seq: must have shape [T, 3] with T >= 1, got {qpos.shape}")
    if min(width, height, fps) < 1:
        raise ValueError(f"width, height, fps: must be >= 1, got {width}, {height}, {fps}")
    model = episode_model(env.scene, params, width, height)
    data = mujoco.MjData(model)
    shapes = room_shapes(params)
    camera = _top_down_camera(model, shapes.outer_half, width / height, wall_height)
    backend = gl_backend()
    if backend is None:
        raise NoGLError(f"no OpenGL backend ({GL_HINT})")
    try:
        renderer = mujoco.Renderer(model, height, width)
    except Exception as err:  # whatever the GL stack raises: ImportError, RuntimeError, FatalError
        raise NoGLError(f"OpenGL backend {backend!r} failed: {err}") from err
    # Shadows cost 4x the frame time in software GL, and from straight above they hide under the
    # obstacles anyway.
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
    rooms = _moving_rooms(params, qpos, env.scene.cfg.control_period, env.robot.radius)
    frames = []
    with renderer:
        for i in range(len(qpos)):
            if rooms is not None:
                set_room(model, env.scene, jax.tree_util.tree_map(lambda x, i=i: x[i], rooms))
            data.qpos[:3] = qpos[i]  # the pose; a wheeled model's other joints stay at rest
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera)
            _add_walls(renderer.scene, shapes.walls, wall_height)
            _add_trail(renderer.scene, qpos[: i + 1], env.robot, env.sensor.fov)
            views = [renderer.render()]
            if robot_view:
                renderer.update_scene(data, "depth")
                _add_walls(renderer.scene, shapes.walls, wall_height)
                views.append(renderer.render())
            frames.append(np.concatenate(views, axis=1))
    period = env.scene.cfg.control_period
    return _write_gif(frames, Path(path), fps, title, period)


def _moving_rooms(params, qpos, period: float, radius: float):
    """[T] SceneParams: the room at each control step from the reset (None where nothing moves),
    its walkers giving way to a robot of `radius` at the poses `qpos` [T, 3] (its velocity from
    one pose to the next)."""
    if params.motion is None:
        return None
    xy = np.asarray(qpos[:, :2], np.float32)  # [T, 2]
    velocity = np.diff(xy, axis=0, prepend=xy[:1]) / np.float32(period)  # [T, 2]
    step = lambda p, r: (motion.advance(p, period, (*r, radius)), p)  # noqa: E731
    return jax.device_get(jax.lax.scan(step, params, (xy, velocity))[1])


def episode_model(scene, params, width: int, height: int) -> mujoco.MjModel:
    """A copy of the scene's mj_model with this episode's room (`set_room`), for a renderer of
    `width` x `height` pixels; the plane walls are in group `WALL_GROUP`, which the default
    MjvOption does not draw (infinite planes hide the room from above: `render_episode` draws
    them as boxes instead)."""
    model = copy.deepcopy(scene.mj_model)
    set_room(model, scene, params)
    # The slots were compiled unrotated, so C MuJoCo marks them "same rotation as the body" and
    # would ignore geom_quat (MJX does not): every geom gets its own frame.
    model.geom_sameframe[:] = 0
    model.geom_group[scene.wall_ids] = WALL_GROUP
    # Light from straight above, the same everywhere: no bright cone, shadows under the obstacles.
    if hasattr(model, "light_type"):  # mujoco >= 3.3.1; before, a flag
        model.light_type[:] = mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
    else:
        model.light_directional[:] = 1
    model.light_diffuse[:] = 0.4
    model.light_specular[:] = 0.0  # no highlight: a flat floor quantises without banding
    model.vis.headlight.specular[:] = 0.0
    model.vis.headlight.ambient[:] = 0.2
    model.vis.headlight.diffuse[:] = 0.2
    # Near clipping plane 2 cm from the camera (znear is a fraction of the model's extent), so an
    # obstacle the robot touches still shows in its own view.
    model.vis.map.znear = 0.02 / model.stat.extent
    model.vis.global_.offwidth = max(model.vis.global_.offwidth, width)
    model.vis.global_.offheight = max(model.vis.global_.offheight, height)
    return model


def set_room(model: mujoco.MjModel, scene, params) -> None:
    """Puts the room of `params` (one env's SceneParams) into `model` (from `episode_model`): the
    `geom_pos`, `geom_quat` and `geom_size` the MJX model gets from `Scene.geom_fields`."""
    fields = jax.device_get(scene.geom_fields(params))
    model.geom_pos[:] = fields["geom_pos"]
    model.geom_quat[:] = fields["geom_quat"]
    model.geom_size[:] = fields["geom_size"]


def _top_down_camera(model, outer_half: np.ndarray, aspect: float, wall_height: float):
    """A free camera looking straight down, +x to the right and +y up, framing a room whose walls
    reach `outer_half` [2] from its centre."""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (0.0, 0.0, 0.0)
    cam.azimuth, cam.elevation = 90.0, -90.0
    tan = np.tan(np.deg2rad(model.vis.global_.fovy) / 2)
    half = outer_half + MARGIN
    cam.distance = wall_height + max(half[1] / tan, half[0] / (tan * aspect))
    return cam


def _add_geom(scene, kind, size, pos, mat, rgba) -> None:
    if scene.ngeom >= scene.maxgeom:
        return
    mujoco.mjv_initGeom(
        scene.geoms[scene.ngeom],
        kind,
        np.asarray(size, np.float64),
        np.asarray(pos, np.float64),
        np.asarray(mat, np.float64).reshape(9),
        np.asarray(rgba, np.float32),
    )
    scene.ngeom += 1


def _add_line(scene, start, end, width, rgba, kind=mujoco.mjtGeom.mjGEOM_CAPSULE) -> None:
    if scene.ngeom >= scene.maxgeom:
        return
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, kind, np.zeros(3), np.zeros(3), np.eye(3).reshape(9), np.zeros(4))
    mujoco.mjv_connector(
        geom, kind, width, np.asarray(start, np.float64), np.asarray(end, np.float64)
    )
    geom.rgba[:] = rgba
    scene.ngeom += 1


def _add_walls(scene, walls: np.ndarray, wall_height: float) -> None:
    """The walls (`RoomShapes.walls`: [4, 2, 2] centres and half extents) as boxes of `wall_height`."""
    for (x, y), (half_x, half_y) in walls:
        half = (half_x, half_y, wall_height / 2)
        pos = (x, y, wall_height / 2)
        _add_geom(scene, mujoco.mjtGeom.mjGEOM_BOX, half, pos, np.eye(3), WALL_RGBA)


def _add_trail(scene, qpos: np.ndarray, robot, fov: float) -> None:
    """The path so far on the floor, the heading above the robot (a `RobotSpec`) and the
    sensor's field of view `fov` (rad)."""
    z = 0.01
    for a, b in zip(qpos[:-1], qpos[1:], strict=True):
        if np.linalg.norm(b[:2] - a[:2]) > 1e-4:
            _add_line(scene, (*a[:2], z), (*b[:2], z), 0.025, TRAIL_COLOR)
    x, y, yaw = qpos[-1]
    top = 0.5  # above the robot's top plate (0.45 m): a disc of the base's size, and the heading
    r = robot.radius
    disc = (r, r, 0.005)
    _add_geom(scene, mujoco.mjtGeom.mjGEOM_CYLINDER, disc, (x, y, top), np.eye(3), ROBOT_COLOR)
    tip = (x + 1.6 * r * np.cos(yaw), y + 1.6 * r * np.sin(yaw))
    _add_line(scene, (x, y, top + 0.01), (*tip, top + 0.01), 0.06, HEADING_COLOR, _ARROW)
    eye = np.array([x, y]) + robot.camera_forward * np.array([np.cos(yaw), np.sin(yaw)])
    for side in (-0.5, 0.5):
        angle = yaw + side * fov
        end = eye + FOV_LENGTH * np.array([np.cos(angle), np.sin(angle)])
        _add_line(scene, (*eye, z), (*end, z), 0.01, FOV_COLOR)


def _write_gif(frames, path: Path, fps: int, title: str | None, period: float) -> Path:
    """Frames [H, W, 3] uint8 -> an animated GIF with one shared palette and a time stamp."""
    from PIL import Image, ImageDraw

    images = []
    for i, frame in enumerate(frames):
        image = Image.fromarray(frame)
        draw = ImageDraw.Draw(image)
        label = f"t = {i * period:4.1f} s"
        draw.text((6, 4), f"{title}   {label}" if title else label, fill=(0, 0, 0))
        images.append(image)
    # The last frame holds every colour (the whole path): one palette for all, so none flickers.
    palette = images[-1].quantize(colors=255, method=Image.Quantize.MEDIANCUT)
    frames_p = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    path.parent.mkdir(parents=True, exist_ok=True)
    frames_p[0].save(
        path,
        save_all=True,
        append_images=frames_p[1:],
        duration=max(1, round(1000 / fps)),
        loop=0,
    )
    return path
