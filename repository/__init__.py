"""The dataset store: trial records, content-addressed blobs, the index, exports.

- ``blobs``: MCAP files and logs, named by the sha256 of their bytes, in a local
  folder or an S3-compatible bucket (fsspec); immutable once written, checked on read.
- ``index``: the trial records and users, in SQLAlchemy (SQLite or PostgreSQL), and
  the queries the archive answers.
- ``export``: observation-action pairs for learning, written by the formats that
  ``formats`` lists (``parquet``, ``lerobot``: LeRobot v3).

Imports no other package of the lab.
"""
