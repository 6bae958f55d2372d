"""A crash's reason names the controller's own line, not the library's that raised."""

from __future__ import annotations

from scheduler.outcome import crash_summary

# The stderr of a real trial (dmc-cartpole-balance, a controller sending two values on
# /action): the client library raises the lab's refusal from its own code.
REFUSED = b"""Traceback (most recent call last):
  File "/code/controller.py", line 13, in <module>
    main()
  File "/code/controller.py", line 10, in main
    lab.step()
  File "/opt/labd/site-packages/controllers/client.py", line 355, in step
    self._raise_refusals()  # a command refused before this step: the step did happen
    ^^^^^^^^^^^^^^^^^^^^^^
  File "/opt/labd/site-packages/controllers/client.py", line 415, in _raise_refusals
    raise StatusError(refusals)
controllers.errors.StatusError: the lab refused: publish: msg.data must hold 1 value, one \
per actuator (slide), got 2
"""
NUMPY = b"""Traceback (most recent call last):
  File "/code/controller.py", line 30, in <module>
    run()
  File "/code/policy/linear.py", line 7, in act
    return gains @ state
           ~~~~~~^~~~~~~
  File "/mnt/python/0/site-packages/numpy/core/numeric.py", line 1, in matmul
    raise ValueError("matmul: mismatch")
ValueError: matmul: mismatch
"""
VENDORED = b"""Traceback (most recent call last):
  File "/code/controller.py", line 3, in <module>
    import helper
  File "/code/vendor/site-packages/helper/__init__.py", line 2, in <module>
    raise ImportError("no")
ImportError: no
"""
CHAINED = b"""Traceback (most recent call last):
  File "/code/controller.py", line 5, in load
    return json.load(f)
  File "/usr/lib/python3.11/json/__init__.py", line 293, in load
    raise JSONDecodeError("Expecting value", s, 0)
json.decoder.JSONDecodeError: Expecting value: line 1 column 1 (char 0)

The above exception was the direct cause of the following exception:

Traceback (most recent call last):
  File "/code/controller.py", line 20, in <module>
    weights = load()
  File "/code/controller.py", line 7, in load
    raise RuntimeError("weights.json is not JSON") from err
RuntimeError: weights.json is not JSON
"""
ELSEWHERE = b"""Traceback (most recent call last):
  File "<frozen runpy>", line 198, in _run_module_as_main
  File "/usr/lib/python3.11/runpy.py", line 88, in _run_code
    exec(code, run_globals)
  File "/usr/lib/python3.11/site-packages/pkg/__main__.py", line 4, in <module>
    raise SystemError("broken")
SystemError: broken
"""
NODE = b"""/opt/labd/node_modules/roslib/build/roslib.js:120
      throw new Error("no service /lab/stepp");
      ^

Error: no service /lab/stepp
    at Service.callService (/opt/labd/node_modules/roslib/build/roslib.js:120:13)
    at step (file:///code/lib/lockstep.mjs:9:11)
    at file:///code/controller.mjs:40:3

Node.js v20.20.2
"""


def test_a_refusal_raised_by_the_client_library_names_the_controllers_line():
    """The lab's refusal, raised inside controllers/client.py, is reported at the line of
    the controller's that called the library (the real traceback of such a trial)."""
    assert crash_summary(REFUSED) == (
        "controllers.errors.StatusError: the lab refused: publish: msg.data must hold 1 value,"
        " one per actuator (slide), got 2 (/code/controller.py, line 10, in main)"
    )


def test_the_innermost_frame_of_the_controllers_own_files_is_named():
    """An error raised in an installed package names the controller's module that called
    it; a package vendored in the repository is not the controller's own; with chained
    exceptions, the frame is of the traceback the controller died of."""
    assert crash_summary(NUMPY).endswith("(/code/policy/linear.py, line 7, in act)")
    assert crash_summary(VENDORED).endswith("(/code/controller.py, line 3, in <module>)")
    assert crash_summary(CHAINED) == (
        "RuntimeError: weights.json is not JSON (/code/controller.py, line 7, in load)"
    )


def test_without_a_frame_of_the_controllers_the_innermost_is_named():
    """A traceback with no frame in the controller's files (a command that runs an
    installed module) still names where it was raised."""
    assert crash_summary(ELSEWHERE) == (
        "SystemError: broken (/usr/lib/python3.11/site-packages/pkg/__main__.py, line 4,"
        " in <module>)"
    )


def test_a_node_error_thrown_in_roslib_names_the_controllers_frame():
    """Node's stack is innermost first: the first frame in the controller's own files,
    past roslib's."""
    assert crash_summary(NODE) == (
        "Error: no service /lab/stepp (/code/lib/lockstep.mjs, line 9, in step)"
    )
