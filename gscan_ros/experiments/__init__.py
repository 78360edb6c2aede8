"""experiments layer: plans of many training runs, the runner that brings each to "done"
(`gscan-ros experiment`), and the paper's tables from their results (`gscan-ros report`).

It drives training through `gscan-ros` subprocesses and reads what they write; training
never imports it.
"""
