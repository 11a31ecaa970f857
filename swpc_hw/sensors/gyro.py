"""Gyro messages: ROS 2 ``sensor_msgs/msg/Imu`` in CDR, as a robot's IMU driver sends them.

A real robot's IMU driver publishes ``sensor_msgs/msg/Imu`` on ROS 2, and
zenoh-bridge-ros2dds forwards it, CDR-serialised (zenoh encoding ``application/cdr``), on a
zenoh key (swpc's is ``imu/<robot>/data``).  swpc uses the angular velocity about z (the
yaw rate of R, rad/s) and the header's stamp (s, the IMU driver's clock); the orientation
and the linear acceleration are marked "not provided" by swpc's simulator (covariance
element 0 = -1, REP 145) and ignored on reception.  (De)serialised with rosbags' type
store, never by hand, as the poses of :mod:`swpc_hw.sensors.mocap`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from swpc_hw.errors import SwpcError
from swpc_hw.sensors.mocap import CDR_ENCODING, ros2_typestore

IMU = "sensor_msgs/msg/Imu"
IMU_ENCODING = CDR_ENCODING
_DEG = math.pi / 180.0


class ImuDecodeError(SwpcError, ValueError):
    """An IMU payload could not be decoded."""


@dataclass(frozen=True)
class GyroOptions:
    """A z gyro fixed to R (SI: rad/s, rad/s/sqrt(Hz), rad/s/sqrt(s)): the simulator's
    (:mod:`simulators.offline.datagen_imu` has its model) and the one a plan without motion
    capture assumes.  The defaults: a pessimistic MEMS gyro, slow thermal drift included."""

    rate: float = 200.0
    noise_density: float = 0.005 * _DEG
    bias: float = 0.1 * _DEG
    bias_walk: float = 1e-4 * _DEG
    scale_error: float = 0.003

    @classmethod
    def from_human(
        cls, rate: float, noise: float, bias: float, bias_walk: float, scale_error: float
    ) -> GyroOptions:
        """From the units people write (the command line's, the settings'): Hz,
        deg/s/sqrt(Hz), deg/s, deg/s/sqrt(s) and %."""
        return cls(rate, noise * _DEG, bias * _DEG, bias_walk * _DEG, scale_error / 100.0)

    def human(self) -> tuple[float, float, float, float, float]:
        """``(rate, noise, bias, bias_walk, scale_error)`` in :meth:`from_human`'s units."""
        return (
            self.rate,
            self.noise_density / _DEG,
            self.bias / _DEG,
            self.bias_walk / _DEG,
            self.scale_error * 100.0,
        )


@dataclass(frozen=True)
class GyroSample:
    """The angular velocity of the IMU's frame (rad/s) with its source time stamp (s)."""

    t: float
    wz: float
    wx: float = 0.0
    wy: float = 0.0
    frame_id: str = ""
    wz_variance: float = 0.0
    """Variance of ``wz`` (rad^2/s^2) as the message's covariance says; 0: unknown."""


def encode_imu(g: GyroSample, frame_id: str = "base_link") -> bytes:
    """CDR-serialised ``sensor_msgs/msg/Imu`` (little endian, as ROS 2 sends): the angular
    velocity and its covariance (``wz_variance`` on the z diagonal); orientation and
    linear acceleration not provided (their covariance's first element -1)."""
    ts = ros2_typestore()
    T = ts.types
    sec = math.floor(g.t)
    nanosec = min(round((g.t - sec) * 1e9), 999_999_999)
    not_provided = np.zeros(9)
    not_provided[0] = -1.0
    cov = np.zeros(9)
    cov[8] = g.wz_variance
    msg = T[IMU](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(nanosec)),
            frame_id=g.frame_id or frame_id,
        ),
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=not_provided,
        angular_velocity=T["geometry_msgs/msg/Vector3"](x=g.wx, y=g.wy, z=g.wz),
        angular_velocity_covariance=cov,
        linear_acceleration=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        linear_acceleration_covariance=not_provided.copy(),
    )
    return bytes(ts.serialize_cdr(msg, IMU))


def decode_imu(payload: bytes) -> GyroSample:
    """The gyro part of a CDR ``sensor_msgs/msg/Imu``; :class:`ImuDecodeError` if it is not
    one."""
    if len(payload) < 4 or payload[0] != 0 or payload[1] not in (0, 1):
        raise ImuDecodeError(f"sensor_msgs/Imu: not CDR (first bytes {bytes(payload[:4]).hex()})")
    try:
        msg = ros2_typestore().deserialize_cdr(bytes(payload), IMU)
    except Exception as exc:  # rosbags raises several types for malformed input
        raise ImuDecodeError(f"sensor_msgs/Imu: {exc}") from exc
    st, w = msg.header.stamp, msg.angular_velocity
    return GyroSample(
        st.sec + st.nanosec * 1e-9,
        float(w.z),
        float(w.x),
        float(w.y),
        frame_id=msg.header.frame_id,
        wz_variance=float(msg.angular_velocity_covariance[8]),
    )
