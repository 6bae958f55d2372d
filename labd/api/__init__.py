"""The HTTP API of the lab: the archive to read, trials to submit (``app``), served by
uvicorn on the lab's event loop (``server``)."""
