"""Reading a rosbag2 recording without ROS: the `rosbags` library (`pip install rosbags`), imported
only when a bag is read. numpy only otherwise; used by `python -m jaxnav.replay` and
`python -m jaxnav_robot.calibrate`.
"""

from __future__ import annotations

from pathlib import Path

IMAGE, SCAN = "sensor_msgs/msg/Image", "sensor_msgs/msg/LaserScan"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"


class BagError(ValueError):
    """A bag that cannot be read, or rosbags missing; one line naming the bag."""


def open_bag(bag):
    """(the opened rosbags Reader of the rosbag2 folder `bag`, its typestore); a BagError where
    the folder is no rosbag2, rosbags is missing or the storage cannot be opened. Close the
    reader when done."""
    bag = Path(bag)
    if not (bag / "metadata.yaml").is_file():
        raise BagError(f"{bag}: no such rosbag2 (a folder holding metadata.yaml)")
    try:
        from rosbags.rosbag2 import Reader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise BagError(
            "reading a rosbag2 needs the 'rosbags' package (pip install rosbags)"
        ) from None
    try:
        reader = Reader(bag)
        reader.open()
    except Exception as err:  # noqa: BLE001 - rosbags raises several kinds for a broken bag
        raise BagError(f"{bag}: unreadable rosbag2 ({err})") from None
    # The message types read here are the same in every ROS 2 distribution.
    return reader, get_typestore(Stores.ROS2_HUMBLE)


def decoded(bag, reader, connections, typestore):
    """(ns, topic, message) of each message on `connections`, in recorded time order across them;
    a BagError naming the bag where its storage or a message cannot be read (a message is never
    skipped: without it a replay would show a run that never happened)."""
    counts, done = dict.fromkeys((c.topic for c in connections), 0), 0
    messages = iter(reader.messages(connections))
    while True:
        try:
            connection, ns, raw = next(messages)
        except StopIteration:
            return
        except Exception as err:  # noqa: BLE001 - sqlite3, apsw or mcap errors: damaged storage
            raise BagError(f"{bag}: unreadable rosbag2 after {done} messages ({err})") from None
        counts[connection.topic] += 1
        try:
            msg = typestore.deserialize_cdr(raw, connection.msgtype)
        except Exception as err:  # noqa: BLE001 - truncated CDR: SerdeError, struct.error, ...
            raise BagError(
                f"{bag}: {connection.topic}: message {counts[connection.topic]} on that topic "
                f"cannot be decoded as {connection.msgtype} ({err}); the bag is damaged"
            ) from None
        done += 1
        yield ns, connection.topic, msg


def listing(topics: dict[str, str]) -> str:
    """The bag's topics, "name (type)", for error messages."""
    return ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "none"
