"""The rl-zoo3 hyperparameters of the project, one YAML file per algorithm, shipped as package data."""
