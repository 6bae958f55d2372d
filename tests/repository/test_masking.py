"""Secrets kept out of what the lab prints (repository.masking): one rule for URLs,
``NAME=VALUE`` options and free text."""

from __future__ import annotations

import pytest

from repository.masking import mask_option, mask_text, mask_url


@pytest.mark.parametrize(
    ("url", "shown"),
    [
        (
            "postgresql+psycopg://lab:hunter2@db:5432/lab",
            "postgresql+psycopg://lab:***@db:5432/lab",
        ),
        ("postgresql://lab@db/lab?password=hunter2", "postgresql://lab@db/lab?password=***"),
        (
            "postgresql://lab@db/lab?sslmode=require&sslpassword=x",
            "postgresql://lab@db/lab?sslmode=***&sslpassword=***",
        ),
        (
            "https://auth.example.org/check?token=T#access_token=A",
            "https://auth.example.org/check?token=***#access_token=***",
        ),
        ("https://auth.example.org/check?T0KEN", "https://auth.example.org/check?***"),
        ("https://ghp_T0KEN@github.example.org/a/b.git", "https://***@github.example.org/a/b.git"),
        ("ssh://git@host.example.org/a/b.git", "ssh://git@host.example.org/a/b.git"),
        ("http://u:p@ss@host/x", "http://u:***@host/x"),  # an "@" in the password
        ("postgresql://u:pa/ss@db/lab", "postgresql://u:***@db/lab"),  # SQLAlchemy takes "/"
        ("postgresql://u:p?w@db/lab", "postgresql://u:***@db/lab"),
        ("http://[::1]:8080/x?a=1", "http://[::1]:8080/x?a=***"),
        ("http://host:8080/a@b", "http://host:8080/a@b"),  # a port, and an "@" in the path
        ("s3://lab-archive/records", "s3://lab-archive/records"),
        ("sqlite:////srv/lab/index.sqlite", "sqlite:////srv/lab/index.sqlite"),
        ("/srv/lab/blobs", "/srv/lab/blobs"),
    ],
)
def test_a_url_keeps_where_it_points_and_loses_its_secrets(url, shown):
    """Passwords, query and fragment values, and an http user name alone, are masked;
    scheme, host, port and path stay."""
    assert mask_url(url) == shown


def test_an_option_is_masked_by_its_name_or_as_the_url_it_holds():
    """A NAME=VALUE option named for a credential is masked whole, one holding a URL is
    masked as a URL, any other kept."""
    assert mask_option("aws_secret_access_key", "abc") == "***"
    assert mask_option("aws_session_token", "abc") == "***"
    assert mask_option("key", "abc") == "***"
    assert mask_option("endpoint_url", "http://minio:pw@s3:9000") == "http://minio:***@s3:9000"
    assert mask_option("region_name", "eu-west-1") == "eu-west-1"


def test_every_url_in_a_text_is_masked():
    """Git's words, or an exception's, keep their sense and lose the URLs' secrets."""
    said = (
        "fatal: unable to access 'https://h.example/r.git/?token=T': Could not resolve;"
        ' endpoint "http://minio:pw@s3:9000/bucket?X-Amz-Signature=S"'
    )
    assert mask_text(said) == (
        "fatal: unable to access 'https://h.example/r.git/?token=***': Could not resolve;"
        ' endpoint "http://minio:***@s3:9000/bucket?X-Amz-Signature=***"'
    )
