"""The dataset store: trial records, content-addressed blobs, the index, exports.

- ``blobs``: MCAP files and logs, named by the sha256 of their bytes, in a local
  folder or an S3-compatible bucket (fsspec); immutable once written, checked on read.
- ``index``: the trial records and users, in SQLAlchemy (SQLite or PostgreSQL), and
  the queries the archive answers.
- ``export``: observation-action pairs for learning, written by the formats that
  ``formats`` lists (``parquet``, ``lerobot``: LeRobot v3).
- ``digests``, ``well_known``, ``units``: what the whole lab shares, defined once here,
  the lowest package every other may import: canonical JSON and the manifest digest,
  the names of topics, files and artifacts, sizes and moments.

Imports no other package of the lab.
"""
