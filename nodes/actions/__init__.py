"""The long-running drive operations as ROS 2 actions.

Owner: the actions' own single-threaded executor runs the goals as coroutines (it serves cancels
and other goals while one waits); what blocks in the driver (homing, a move's start and its last
wait, a trajectory goal's start) runs on a worker of its own, a trajectory on its group's thread
(:mod:`motor_driver.follow`).

- :mod:`.driver_actions`: ``home_joint`` and ``move_joint`` (feedback while they run, a cancel
  that stops the joint), and each trajectory group's action server
- :mod:`.follow_trajectory`: ``<group>/follow_joint_trajectory``
  (control_msgs/action/FollowJointTrajectory), as joint_trajectory_controller serves it
"""
