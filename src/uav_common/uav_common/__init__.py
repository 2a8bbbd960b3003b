"""ROS helpers shared by the simulator, policy and trainer nodes: the topic contract, parameter
declaration and the node runner. No simulator, no torch: a drone that runs only the policy installs
this and uav_policy."""
