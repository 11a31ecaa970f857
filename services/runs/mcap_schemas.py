"""The JSON schemas of the MCAP file's channels in profile ``foxglove`` (the default):
Foxglove's own (``foxglove.PoseInFrame``, ``foxglove.FrameTransform``, ``foxglove.Log``,
``foxglove.SceneUpdate``), ROS's messages in JSON (``sensor_msgs/msg/JointState``,
``sensor_msgs/msg/Imu``, ``std_msgs/msg/String``) and the run's own ``swpc.Segment``.
Written by :class:`services.runs.mcap.McapRecorder`; its module docstring says which topic
carries which.
"""

from __future__ import annotations

_TIME = {
    "type": "object",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_VECTOR3 = {
    "type": "object",
    "title": "foxglove.Vector3",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z")},
    "required": ["x", "y", "z"],
}
_QUATERNION = {
    "type": "object",
    "title": "foxglove.Quaternion",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
    "required": ["x", "y", "z", "w"],
}
POSE_IN_FRAME = {
    "title": "foxglove.PoseInFrame",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": {
            "title": "foxglove.Pose",
            "type": "object",
            "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
            "required": ["position", "orientation"],
        },
    },
    "required": ["timestamp", "frame_id", "pose"],
}
FRAME_TRANSFORM = {
    "title": "foxglove.FrameTransform",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VECTOR3,
        "rotation": _QUATERNION,
    },
    "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation", "rotation"],
}
LOG = {
    "title": "foxglove.Log",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "level": {"type": "integer", "description": "1 debug, 2 info, 3 warning, 4 error"},
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
    "required": ["timestamp", "level", "message", "name", "file", "line"],
}
_HEADER = {
    "type": "object",
    "title": "std_msgs/msg/Header",
    "properties": {"stamp": _TIME, "frame_id": {"type": "string"}},
    "required": ["stamp", "frame_id"],
}
_NUMBERS = {"type": "array", "items": {"type": "number"}}
ENCODERS = {
    "title": "sensor_msgs/msg/JointState",
    "type": "object",
    "properties": {
        "header": _HEADER,
        "name": {"type": "array", "items": {"type": "string"},
                 "description": "the URDF's joints: steer_<id>, wheel_<id>"},
        "position": {**_NUMBERS, "description": "reported theta_hat and cumulative psi, rad"},
        "velocity": _NUMBERS,
        "effort": _NUMBERS,
    },
    "required": ["header", "name", "position", "velocity", "effort"],
}  # fmt: skip
"""A module's encoders as ROS's JointState (in JSON here), named as the URDF of
``/robot_description`` names its joints, so a viewer moves the robot's model with them."""
SEGMENT = {
    "title": "swpc.Segment",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "static_module": {"type": "integer"},
        "start": {"type": "number", "description": "window start, dataset clock s"},
        "end": {"type": "number", "description": "window end, dataset clock s"},
        "start_time": _TIME,
        "end_time": _TIME,
    },
}
"""A spin window: ``start``/``end`` on the dataset's clock (segments.csv), ``start_time``
/``end_time`` the same instants on the file's log time (epoch), as a viewer's timeline
shows them."""
_COVARIANCE = {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9}
GYRO = {
    "title": "sensor_msgs/msg/Imu",
    "type": "object",
    "properties": {
        "header": _HEADER,
        "orientation": _QUATERNION,
        "orientation_covariance": _COVARIANCE,
        "angular_velocity": {**_VECTOR3, "description": "z: the gyro's yaw rate, rad/s"},
        "angular_velocity_covariance": _COVARIANCE,
        "linear_acceleration": _VECTOR3,
        "linear_acceleration_covariance": _COVARIANCE,
    },
    "required": ["header", "angular_velocity"],
}
"""The gyro as ROS's Imu (in JSON here): orientation and acceleration not provided (their
covariance's first element -1), as :func:`swpc_hw.sensors.gyro.encode_imu` sends it."""
STRING = {
    "title": "std_msgs/msg/String",
    "type": "object",
    "properties": {"data": {"type": "string"}},
    "required": ["data"],
}
"""``/robot_description``: the URDF, as Foxglove's 3D panel takes it from a topic."""
_COLOR = {
    "type": "object",
    "title": "foxglove.Color",
    "properties": {k: {"type": "number", "minimum": 0, "maximum": 1} for k in "rgba"},
    "required": ["r", "g", "b", "a"],
}
_POSE = {
    "type": "object",
    "title": "foxglove.Pose",
    "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
    "required": ["position", "orientation"],
}
_ARRAY = {"type": "array", "maxItems": 0}
SCENE_UPDATE = {
    "title": "foxglove.SceneUpdate",
    "type": "object",
    "properties": {
        "deletions": _ARRAY,
        "entities": {
            "type": "array",
            "items": {
                "title": "foxglove.SceneEntity",
                "type": "object",
                "properties": {
                    "timestamp": _TIME,
                    "frame_id": {"type": "string"},
                    "id": {"type": "string"},
                    "lifetime": _TIME,
                    "frame_locked": {"type": "boolean"},
                    "metadata": _ARRAY, "arrows": _ARRAY, "cubes": _ARRAY, "spheres": _ARRAY,
                    "cylinders": _ARRAY, "triangles": _ARRAY, "texts": _ARRAY,
                    "models": _ARRAY,
                    "lines": {
                        "type": "array",
                        "items": {
                            "title": "foxglove.LinePrimitive",
                            "type": "object",
                            "properties": {
                                "type": {"type": "integer", "description": "1: line loop"},
                                "pose": _POSE,
                                "thickness": {"type": "number"},
                                "scale_invariant": {"type": "boolean"},
                                "points": {"type": "array", "items": _VECTOR3},
                                "color": _COLOR,
                                "colors": _ARRAY,
                                "indices": _ARRAY,
                            },
                            "required": ["type", "pose", "thickness", "points", "color"],
                        },
                    },
                },
                "required": ["timestamp", "frame_id", "id", "lines"],
            },
        },
    },
    "required": ["deletions", "entities"],
}  # fmt: skip
"""``/calibration/circles``: the fitted circle of each spin (a subset of Foxglove's
SceneUpdate: line loops only)."""
