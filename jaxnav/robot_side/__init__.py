"""What runs on the robot: numpy only, importable without jax (and copied as `jaxnav_robot/` by
`python -m jaxnav.export RUN --bundle DIR`): the policy's forward pass (`policy`), sensor reading ->
observation -> velocity command (`observation`), the camera mount from the floor (`calibrate`,
also a command), reading rosbag2 recordings (`bag`, with the `rosbags` library) and the ROS 2 node
(`ros_node`: its logic, `ControlLoop`, is plain numpy; rclpy is imported lazily; none of these
three is imported here, so that `python -m jaxnav.robot_side.<module>` runs it only once).
"""

from .observation import Controller, Sensor, Twist
from .policy import NumpyPolicy

__all__ = ["Controller", "NumpyPolicy", "Sensor", "Twist"]
