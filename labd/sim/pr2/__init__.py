"""pr2-table: a PR2-like mobile manipulator picks an object and places it on a table.

``model`` is the robot as MJCF, ``scene`` the table and what stands on it, ``physics``
the accessors, ``motion`` how commands become joint setpoints (trajectories and arm
IK), ``topics`` the messages, and ``table`` the task, its factory and ``TASK``.
"""
