"""uav_trainer: replay memory, the Double-Dueling DQN learner and the trainer node."""
