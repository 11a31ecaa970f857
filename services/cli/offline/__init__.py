"""The ``swpc`` subcommands that work on files and models, not on a robot: generate data
(``datagen``), solve it (``solve``), plan a protocol (``plan``), export a kinematic file
(``export``), odometry and the square path (``odometry``, ``validate``).  One module per
subcommand, discovered as the robot's are (:func:`services.cli.subcommand_modules`)."""
