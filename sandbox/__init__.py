"""Isolation backends behind one interface: Docker and bubblewrap.

Empty until the trial runner lands (see DESIGN.md). Imports no other package of the lab.
"""
