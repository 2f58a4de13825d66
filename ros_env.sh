# Source before anything that may start rclpy / DDS (tests, demo, experiments):
#   . ./ros_env.sh
# Keeps DDS discovery on this machine and picks a ROS domain of its own unless one is set.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( (RANDOM % 100) + 1 ))}"
