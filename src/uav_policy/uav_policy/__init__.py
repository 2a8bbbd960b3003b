"""uav_policy: D3QN-SAM and D3QN-CNN Q-networks and the policy node."""
