"""What runs on the robot: numpy only, importable without jax (and copied as `jaxnav_robot/` by
`python -m jaxnav.export RUN --bundle DIR`): the policy's forward pass (`policy`), sensor reading ->
observation -> velocity command (`observation`) and the ROS 2 node (`ros_node`, rclpy imported lazily).
"""

from .observation import Controller, Sensor, Twist
from .policy import NumpyPolicy

__all__ = ["Controller", "NumpyPolicy", "Sensor", "Twist"]
