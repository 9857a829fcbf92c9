"""The evaluation's policies by name, without what runs them (the CLI's parser reads these without importing torch)."""

POLICIES = ("net", "oracle", "random")
SCRIPTED = ("oracle", "random")  # policies that need no checkpoint
DESCRIPTION = {
    "net": "the checkpoint's greedy policy",
    "oracle": "the scripted oracle (reads object poses from the simulator: the ceiling)",
    "random": "uniformly random valid actions (the floor; picks only where clear under the clearance rule)",
}
