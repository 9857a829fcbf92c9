"""PyBullet simulation of the paper's tasks, behind the Env interface."""
