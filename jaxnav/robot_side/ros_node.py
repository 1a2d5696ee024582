"""ROS 2 node: depth image (or LaserScan) -> exported policy -> geometry_msgs/Twist, one per message.

On the robot, in the folder `python -m jaxnav.export RUN --bundle DIR` wrote (numpy and rclpy only):

    python3 -m jaxnav_robot.ros_node --policy policy.npz                        # /camera/depth/image_raw
    python3 -m jaxnav_robot.ros_node --policy policy.npz --scan --topic /scan   # a LaserScan instead
    python3 -m jaxnav_robot.ros_node --policy policy.npz --ros-args -r cmd_vel:=commands/velocity

(`python -m jaxnav.robot_side.ros_node` works too where jaxnav is installed.) The flags set the
defaults of ROS 2 parameters of the same names (policy, topic, scan, cmd_vel, speed_calibration,
vfov_deg, band_deg, tilt_deg), which `--ros-args -p` overrides. Depth images may be 32FC1 (metres) or
16UC1 (millimetres); only rows within +-band_deg of the horizon are read (see
`observation.horizon_rows`), as the simulator's sensor is a horizontal fan. On shutdown (Ctrl-C) a zero
Twist is sent.

rclpy and the message packages are imported inside `main` only: the conversion functions below are
plain functions of message fields, testable without ROS.
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from .observation import Controller, Twist, horizon_rows
from .policy import NumpyPolicy

ASTRA_VFOV_DEG = 49.5  # Orbbec Astra vertical field of view (the simulator has no vertical extent)

# sensor_msgs/Image encodings of depth: (numpy dtype, metres per unit)
DEPTH_ENCODINGS = {
    "32FC1": (np.float32, 1.0),
    "16UC1": (np.uint16, 0.001),
    "mono16": (np.uint16, 0.001),
}


def image_msg_to_array(
    encoding: str, height: int, width: int, data, step: int, is_bigendian: bool = False
) -> np.ndarray:
    """[height, width] float32 depth in metres from sensor_msgs/Image fields.

    `step` is the row length in bytes, which may exceed width * pixel size (padding). 16-bit depth is
    in millimetres; its 0 (no data) stays 0, which the observation ignores as invalid.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"image encoding '{encoding}' is not depth; use {sorted(DEPTH_ENCODINGS)}")
    dtype, scale = DEPTH_ENCODINGS[encoding]
    dtype = np.dtype(dtype).newbyteorder(">" if is_bigendian else "<")
    row_bytes = width * dtype.itemsize
    buf = np.frombuffer(bytes(data), np.uint8)
    if step < row_bytes or buf.size < height * step:
        raise ValueError(
            f"image data of {buf.size} bytes, step {step}: too short for {height}x{width} {encoding}"
        )
    rows = buf[: height * step].reshape(height, step)[:, :row_bytes]
    pixels = np.ascontiguousarray(rows).view(dtype).reshape(height, width)
    return pixels.astype(np.float32) * np.float32(scale)


def scan_msg_to_arrays(ranges, angle_min: float, angle_increment: float):
    """(ranges [N] float32 m, angles [N] float64 rad) from sensor_msgs/LaserScan fields."""
    ranges = np.asarray(ranges, np.float32)
    return ranges, angle_min + angle_increment * np.arange(ranges.size)


def twist_msg(twist: Twist, msg_cls):
    """A geometry_msgs/Twist (`msg_cls`) holding the command."""
    msg = msg_cls()
    msg.linear.x, msg.angular.z = float(twist.linear), float(twist.angular)
    return msg


def parse_args(argv=None):
    """Flags (defaults of the node's ROS parameters) and the rest (for rclpy: --ros-args ...)."""
    p = argparse.ArgumentParser(prog="ros_node", description=__doc__.splitlines()[0])
    p.add_argument("--policy", default="policy.npz", help="exported policy (.npz)")
    p.add_argument("--topic", default="/camera/depth/image_raw", help="depth image or scan topic")
    p.add_argument("--scan", action="store_true", help="the topic is a sensor_msgs/LaserScan")
    p.add_argument("--cmd-vel", default="cmd_vel", help="geometry_msgs/Twist output topic")
    p.add_argument("--speed-calibration", type=float, default=1.0, help="multiplies both speeds")
    p.add_argument("--vfov-deg", type=float, default=ASTRA_VFOV_DEG, help="camera")
    p.add_argument("--band-deg", type=float, default=2.0, help="rows within +-this of horizon")
    p.add_argument("--tilt-deg", type=float, default=0.0, help="camera pitch, positive = down")
    return p.parse_known_args(argv)


def _make_node(args):
    """The rclpy node, its parameters declared with the flags' values as defaults."""
    from geometry_msgs.msg import Twist as TwistMsg
    from rclpy.node import Node
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Image, LaserScan

    class PolicyNode(Node):
        def __init__(self):
            super().__init__("jaxnav_policy")
            get = {k: self.declare_parameter(k, v).value for k, v in vars(args).items()}
            policy = NumpyPolicy.from_npz(get["policy"])
            self.controller = Controller(policy, speed_calibration=get["speed_calibration"])
            self.band = (
                math.radians(get["vfov_deg"]),
                get["band_deg"],
                math.radians(get["tilt_deg"]),
            )
            self.pub = self.create_publisher(TwistMsg, get["cmd_vel"], 10)
            msg_type, callback = (
                (LaserScan, self.on_scan) if get["scan"] else (Image, self.on_image)
            )
            self.create_subscription(msg_type, get["topic"], callback, qos_profile_sensor_data)
            self.get_logger().info(f"{get['policy']}: {get['topic']} -> {get['cmd_vel']}")

        def on_image(self, msg):
            depth = image_msg_to_array(
                msg.encoding, msg.height, msg.width, msg.data, msg.step, bool(msg.is_bigendian)
            )
            vfov, band, tilt = self.band
            rows = horizon_rows(msg.height, vfov, band, tilt) if band > 0 else None
            self.pub.publish(twist_msg(self.controller.image_to_twist(depth, rows), TwistMsg))

        def on_scan(self, msg):
            ranges, angles = scan_msg_to_arrays(msg.ranges, msg.angle_min, msg.angle_increment)
            self.pub.publish(twist_msg(self.controller.scan_to_twist(ranges, angles), TwistMsg))

        def stop(self):
            try:  # best effort: the context may be gone if rclpy handled the signal itself
                self.pub.publish(twist_msg(Twist(0.0, 0.0), TwistMsg))
            except Exception as err:  # noqa: BLE001
                print(f"could not send the stop command: {err}", file=sys.stderr)

    return PolicyNode()


def main(argv=None) -> int:
    args, ros_args = parse_args(argv)
    import rclpy

    argv = [sys.argv[0], *ros_args]
    try:  # Humble and later: rclpy's own SIGINT handler would shut the context down before the
        # stop command below could be sent; Python's default one raises KeyboardInterrupt instead.
        from rclpy.signals import SignalHandlerOptions

        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except ImportError:
        rclpy.init(args=argv)
    node = _make_node(args)
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.stop()  # the robot must not keep driving on the last command
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
