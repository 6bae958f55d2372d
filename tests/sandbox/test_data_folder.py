"""The data a controller learns from: readable at LAB_DATA_DIR, and never writable."""

from __future__ import annotations

from pathlib import Path

from tests.sandbox.conftest import Controllers, lines


async def test_the_data_folder_is_readable_and_read_only(
    controllers: Controllers, workdir: Path, tmp_path: Path
) -> None:
    """LAB_DATA_DIR names the folder; its files read, and writing, deleting or creating
    anything there fails with a read-only file system, on either backend."""
    data = workdir / f"data-{tmp_path.name}"
    (data / "records").mkdir(parents=True, exist_ok=True)
    (data / "records" / "trial-1.mcap").write_bytes(b"pinned bytes")
    for path in (data, data / "records"):
        path.chmod(0o777)  # open to all: only the read-only mount stops a write
    (data / "records" / "trial-1.mcap").chmod(0o666)
    ended = await controllers.run(
        """
        import errno, os
        folder = os.environ["LAB_DATA_DIR"]
        print(folder)
        print(open(os.path.join(folder, "records", "trial-1.mcap"), "rb").read().decode())
        for attempt in (
            lambda: open(os.path.join(folder, "records", "trial-1.mcap"), "ab"),
            lambda: open(os.path.join(folder, "new.txt"), "w"),
            lambda: os.remove(os.path.join(folder, "records", "trial-1.mcap")),
            lambda: os.mkdir(os.path.join(folder, "more")),
        ):
            try:
                attempt()
                print("written")
            except OSError as err:
                print(errno.errorcode[err.errno])
        """,
        data=data,
    )
    assert ended.code == 0, ended.stderr
    assert lines(ended.stdout) == ["/mnt/data", "pinned bytes", *["EROFS"] * 4]
    assert (data / "records" / "trial-1.mcap").read_bytes() == b"pinned bytes"
    assert sorted(p.name for p in data.iterdir()) == ["records"]
