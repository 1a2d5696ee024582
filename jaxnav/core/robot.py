"""TurtleBot 2i constants: Kobuki base, Orbbec Astra depth camera and the action table.

Figures are the manufacturer's public ones (Kobuki user guide, Astra datasheet).
"""

import numpy as np

BASE_RADIUS = 0.177  # m; Kobuki diameter 0.354 m
BASE_MASS = 2.35  # kg; Kobuki base without payload
BASE_HEIGHT = 0.11  # m; top of the Kobuki shell
WHEELBASE = 0.230  # m; distance between the drive wheels
WHEEL_RADIUS = 0.035  # m
MAX_LINEAR_SPEED = 0.7  # m/s; Kobuki top speed
MAX_ANGULAR_SPEED = np.pi  # rad/s; Kobuki top yaw rate, 180 deg/s

CAMERA_FORWARD = 0.12  # m; camera ahead of the base centre
CAMERA_HEIGHT = 0.30  # m; optical centre above the floor
CAMERA_FOV = np.deg2rad(60.0)  # rad; Astra horizontal field of view
CAMERA_RANGE = (0.6, 8.0)  # m; Astra usable depth range
NUM_SECTORS = 8  # the paper's observation: 8 shortest distances

CONTROL_PERIOD = 0.1  # s; commands are sent at 10 Hz

# Actions of the paper: (forward speed fraction, yaw rate fraction) of the top speeds.
# Turning happens in place, as the paper's robot does.
ACTION_NAMES = ("forward", "left", "right")
ACTIONS = np.array([[1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], dtype=np.float32)  # [3, 2]
