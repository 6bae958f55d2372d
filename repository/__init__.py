"""The dataset store: trial records, content-addressed blobs, the index, exports.

Empty until the archive lands (see DESIGN.md). Imports no other package of the lab.
"""
