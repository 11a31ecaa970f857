"""What runs on the robot: odometry on the kinematic file, its drift monitor, the twist
controller and the square path follower, ROS 2 over zenoh (``ros2/``) and the exports
(``export/``)."""
