"""uav_sim: a pybullet quadrotor simulator with a depth camera, and the paper's reward."""
