"""Trial specs, the persistent queue, admission, git resolution and the trial runner.

Empty until the trial and service issues land (see DESIGN.md, "Data flow").
"""
