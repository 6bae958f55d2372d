"""The iRobot Create-like robot and its maze task (``icreate-maze``).

``layout`` draws the maze from the seed, ``tags`` makes the fiducial tags and the
detector that reports them, ``model`` writes the robot and the world as MJCF, and
``maze`` is the task: its physics, topics, reward and the registered ``TASK``.
"""
