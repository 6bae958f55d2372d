"""The lab's configuration: the file, then ``LABD_*`` variables, then flags; every value
checked by its flag's own type; secrets masked when shown; one lab per data folder."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from labd.cli import build_parser
from labd.commands import config
from labd.commands.config import ConfigError, Found
from labd.datalock import DataLock, FolderInUse, holder


def configured(
    argv: list[str], environ: dict[str, str] | None = None
) -> tuple[argparse.Namespace, dict[str, Found]]:
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    found = config.apply(parser, args, config.given(build_parser, argv), environ or {})
    return args, found


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_a_flag_beats_a_variable_which_beats_the_file_which_beats_the_default(tmp_path):
    """Each setting comes from the first source that has it, and says which that was."""
    lab = write(
        tmp_path / "lab.toml",
        '[serve]\nhttp_port = 8181\nbridge_port = 9191\nworkers = 3\ndata = "srv"\n'
        'videos = "asked"\nreservations = true\n',
    )
    args, found = configured(
        ["serve", "--config", str(lab), "--workers", "5"], {"LABD_BRIDGE_PORT": "9292"}
    )
    assert (args.http_port, args.bridge_port, args.workers) == (8181, 9292, 5)
    assert args.videos == "asked" and args.reservations is True
    assert args.data == tmp_path / "srv"  # relative to the file's folder
    assert args.lease == 30.0  # nobody said: the flag's default
    assert found["http_port"].source == f"{lab} [serve]"
    assert found["bridge_port"].source == "LABD_BRIDGE_PORT"
    assert found["workers"].source == "flag"
    assert found["lease"].source == "default"


def test_repeatable_settings_take_lists_tables_and_comma_separated_variables(tmp_path):
    lab = write(
        tmp_path / "lab.toml",
        '[serve]\nrobot = { "maze-1" = "icreate-maze", "arm-1" = "pr2-table" }\n'
        'trusted_proxy = ["10.0.0.0/8"]\n',
    )
    args, _ = configured(
        ["serve", "--config", str(lab)], {"LABD_BLOBS_OPTION": "endpoint_url=http://s3:9000,a=b"}
    )
    assert args.robot == [("maze-1", "icreate-maze"), ("arm-1", "pr2-table")]
    assert args.trusted_proxy == ["10.0.0.0/8"]
    assert args.blobs_option == [("endpoint_url", "http://s3:9000"), ("a", "b")]


@pytest.mark.parametrize(
    ("text", "environ", "message"),
    [
        (
            "[serve]\nhtp_port = 1\n",
            {},
            "htp_port: no setting of labd serve (did you mean http_port?)",
        ),
        ('[serve]\nvideos = "sometimes"\n', {}, "'sometimes' is not one of background, asked"),
        ('[serve]\nworkers = "two"\n', {}, "'two': not a whole number"),
        ("[serve]\nworkers = 1.5\n", {}, "give a whole number"),
        ('[serve]\nreservations = "yes"\n', {}, "give true or false"),
        ('[serve]\nrobot = ["nameless"]\n', {}, "write NAME=VALUE"),
        ("serve = 3\n", {}, "[serve] must be a table"),
        ("[serve\n", {}, "not TOML"),
        ("", {"LABD_HTTP_PORT": "eighty"}, "LABD_HTTP_PORT: 'eighty': not a whole number"),
        ("", {"LABD_LOCKSTEP": "maybe"}, "LABD_LOCKSTEP='maybe': give 1 or 0"),
    ],
)
def test_a_setting_its_flag_would_refuse_is_refused_with_where_it_is(
    tmp_path, text, environ, message
):
    lab = write(tmp_path / "lab.toml", text)
    with pytest.raises(ConfigError) as caught:
        configured(["serve", "--config", str(lab)], environ)
    assert message in str(caught.value)


def test_an_operator_command_takes_the_labs_own_settings_from_its_table(tmp_path):
    """`labd users add` reads [serve]'s data and database: it opens the lab's index."""
    lab = write(
        tmp_path / "lab.toml",
        '[serve]\ndata = "/srv/lab"\ndatabase = "postgresql+psycopg://lab@db/lab"\n'
        "http_port = 8181\n",  # not a setting of users add: left to serve
    )
    args, found = configured(["users", "add", "carol", "--config", str(lab)])
    assert args.data == Path("/srv/lab")
    assert args.database == "postgresql+psycopg://lab@db/lab"
    assert "http_port" not in found


def test_the_default_file_is_labd_toml_in_the_working_folder(tmp_path, monkeypatch):
    write(tmp_path / "labd.toml", "[serve]\nhttp_port = 8282\n")
    monkeypatch.chdir(tmp_path)
    args, _ = configured(["serve"])
    assert args.http_port == 8282
    with pytest.raises(ConfigError, match="no such configuration file"):
        configured(["serve", "--config", str(tmp_path / "missing.toml")])


def test_config_show_masks_secrets_and_names_sources(tmp_path):
    lab = write(
        tmp_path / "lab.toml",
        '[serve]\ndatabase = "postgresql+psycopg://lab:hunter2@db:5432/lab"\n'
        'blobs_option = ["endpoint_url=http://s3:9000", "secret=s3cr3t", "key=k3y"]\n',
    )
    done = subprocess.run(
        [sys.executable, "-m", "labd", "config", "show", "--config", str(lab), "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    shown = json.loads(done.stdout)
    assert "hunter2" not in done.stdout and "s3cr3t" not in done.stdout and "k3y" not in done.stdout
    assert shown["settings"]["database"] == "postgresql+psycopg://lab:***@db:5432/lab"
    assert shown["settings"]["blobs_option"] == [
        "endpoint_url=http://s3:9000",
        "secret=***",
        "key=***",
    ]
    assert shown["sources"]["database"] == f"{lab} [serve]"
    assert shown["sources"]["http_port"] == "default"


def test_a_data_folder_has_one_holder_and_says_who(tmp_path):
    """A second lab on a folder is refused naming the first's address; once the first
    lets go, the folder is free again."""
    first = DataLock.take(tmp_path)
    first.note(http="http://127.0.0.1:8123")
    assert holder(tmp_path) == {"pid": os.getpid(), "http": "http://127.0.0.1:8123"}
    with pytest.raises(FolderInUse, match=r"in use by the lab at http://127\.0\.0\.1:8123 \(pid"):
        DataLock.take(tmp_path)
    first.release()
    assert holder(tmp_path) is None
    DataLock.take(tmp_path).release()


def test_the_documented_example_is_a_configuration_the_lab_takes(tmp_path):
    """docs/service.md's example file applies to `labd serve` and `labd worker` as it says."""
    docs = (Path(__file__).parents[2] / "docs" / "service.md").read_text()
    example = docs.split("## Configuration", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    lab = write(tmp_path / "labd.toml", example)
    args, found = configured(["serve", "--config", str(lab)])
    assert args.robot == [("icreate-1", "icreate-maze"), ("pr2-1", "pr2-table")]
    assert args.data == Path("/srv/lab") and args.reservations is True
    assert args.worker_processes == 2 and args.public_url == "https://lab.example.org"
    assert all(s.source == "default" or s.source.endswith("[serve]") for s in found.values())
    worker, _ = configured(["worker", "--config", str(lab)])
    assert worker.server == "https://lab.example.org"
