"""RoManNet fleet: the RoManNet method as a distributed actor-learner service."""

__version__ = "0.1.0"
