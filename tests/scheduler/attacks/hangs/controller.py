import time

from controllers.client import Lab

lab = Lab.connect()
lab.subscribe("/odom", "nav_msgs/msg/Odometry").get()
while True:  # connected, but never steps
    time.sleep(1)
