"""The lab daemon: the rosbridge server, the robot graph, simulated robots, the recorder."""

__version__ = "0.2.0"
