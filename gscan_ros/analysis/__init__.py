"""analysis layer: what a trained network attends to (paper § "Interpretability and
acquisition"): traces, the size-ordering map and its numbers, and the figures.

Built on model (Policy), data, language and world, so that training (the seed screen),
the nodes (policy_node's live size ordering) and the CLI (`gscan-ros explain`) share it.
"""
