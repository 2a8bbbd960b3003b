"""Measuring policies: flights, tables, statistics, the validation choice, grounding, figures and plots."""

ENSEMBLE_SEP = "+"  # joins an ensemble's weights files in the weights column of results.csv

# What `evaluate --model` flies: the two networks, and the planner (uav_sim.planner) knowing what the last five frames
# showed (planner) or the whole world (planner_all), the task's limit with the four actions, or only the local map of
# the measured depth and odometry (planner_map: what a drone can know).
PLANNERS = {"planner": "stack", "planner_all": "all", "planner_map": "map"}
MODELS = ("sam", "cnn", *PLANNERS)
LABELS = {
    "sam": "D3QN-SAM",
    "cnn": "D3QN-CNN",
    "planner": "planner (5 frames)",
    "planner_all": "planner (all)",
    "planner_map": "planner (local map)",
}
PLANNER_WEIGHTS = "none"  # a planner row's weights column: it flies no weights file
