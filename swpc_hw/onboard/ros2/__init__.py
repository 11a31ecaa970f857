"""ROS 2 on the robot without ROS: rmw_zenoh's wire format, the odometry's ROS 2 messages
and their covariances (pure functions), and the small zenoh edge that publishes them
(docs/ros2.md, "Odometry and TF over zenoh").

:mod:`swpc_hw.onboard.ros2.wire` and :mod:`swpc_hw.onboard.ros2.covariance` need only the
standard library and numpy; :mod:`swpc_hw.onboard.ros2.messages` needs rosbags and
:mod:`swpc_hw.onboard.ros2.publisher` zenoh (the extra ``service``).
:mod:`swpc_hw.onboard.odometry` imports none of them.
"""
