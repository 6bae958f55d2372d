"""Which hosts a lab fetches from (scheduler.hosts): a pure check of addresses, and the
lookup of a name with every address it gives checked, the resolver passed in."""

from __future__ import annotations

import ipaddress

import pytest

from scheduler.errors import HostNotAllowed, Unreachable
from scheduler.hosts import endpoint, kind, literal, pin


@pytest.mark.parametrize(
    ("address", "expected"),
    [
        ("127.0.0.1", "loopback"),
        ("127.255.0.9", "loopback"),
        ("::1", "loopback"),
        ("0.0.0.0", "unspecified"),
        ("::", "unspecified"),
        ("169.254.169.254", "link-local"),  # a cloud's metadata service
        ("fe80::1", "link-local"),
        ("10.0.0.1", "private"),
        ("172.16.5.4", "private"),
        ("192.168.1.1", "private"),
        ("fd00::1", "private"),
        ("224.0.0.1", "multicast"),
        ("ff02::1", "multicast"),
        ("240.0.0.1", "private"),  # Python counts 240/4 among its private networks
        ("100.64.0.1", "non-public"),  # carrier-grade NAT, shared address space
        ("fec0::1", "site-local"),
        ("::ffff:127.0.0.1", "loopback"),  # IPv4-mapped: judged as the IPv4 address
        ("::ffff:10.0.0.1", "private"),
        ("2002:7f00:1::", "loopback"),  # 6to4 around 127.0.0.1
        ("64:ff9b::a9fe:a9fe", "link-local"),  # NAT64 around 169.254.169.254
        ("203.0.113.5", "private"),  # documentation ranges are no one's public address
        ("8.8.8.8", None),
        ("2606:4700::1111", None),
        ("::ffff:8.8.8.8", None),
        ("64:ff9b::808:808", None),
    ],
)
def test_kind_names_what_makes_an_address_not_public(address, expected):
    """Each address that is not public is named by what it is; public ones are None."""
    assert kind(ipaddress.ip_address(address)) == expected


def test_endpoints_of_every_url_form():
    """The host and port git would connect to, for each URL form; none for local ones."""
    assert endpoint("https://git.example.org/r.git", "https") == ("git.example.org", 443)
    assert endpoint("http://git.example.org:8080/r", "http") == ("git.example.org", 8080)
    assert endpoint("git://[::1]:9/r.git", "git") == ("::1", 9)
    assert endpoint("ssh://git@host.example.org/r.git", "ssh") == ("host.example.org", 22)
    assert endpoint("git@host.example.org:team/r.git", "ssh") == ("host.example.org", 22)
    assert endpoint("[::1]:team/r.git", "ssh") == ("::1", 22)
    assert endpoint("/srv/repos/r", "file") is None


def test_literals_include_the_forms_the_c_resolver_reads():
    """``127.1`` and ``0x7f.0.0.1`` are loopback addresses to git, so to the check too."""
    assert literal("127.1") == ipaddress.ip_address("127.0.0.1")
    assert literal("0x7f.0.0.1") == ipaddress.ip_address("127.0.0.1")
    assert literal("2130706433") == ipaddress.ip_address("127.0.0.1")
    assert literal("git.example.org") is None


def test_a_name_is_refused_when_any_of_its_addresses_is_not_public():
    """Every address a name resolves to is checked, not only the first; a public name is
    pinned to its first address; the resolver is asked with the URL's port."""
    asked = []

    def lookup(host: str, port: int) -> list[str]:
        asked.append((host, port))
        return {"public": ["9.9.9.9", "2620:fe::fe"], "mixed": ["8.8.8.8", "127.0.0.1"]}.get(
            host, []
        )

    pinned = pin("https://public/r.git", "public", 443, lookup)
    assert (pinned.addresses, pinned.name) == (("9.9.9.9", "2620:fe::fe"), True)
    assert pinned.resolve == "public:443:9.9.9.9,[2620:fe::fe]"
    with pytest.raises(HostNotAllowed, match="its host mixed resolves to a loopback address"):
        pin("https://mixed/r.git", "mixed", 443, lookup)
    with pytest.raises(Unreachable, match="the repository could not be fetched"):
        pin("https://nowhere/r.git", "nowhere", 443, lookup)
    assert asked == [("public", 443), ("mixed", 443), ("nowhere", 443)]


def test_a_name_that_does_not_resolve_is_said_like_any_network_failure():
    """A resolver error becomes Unreachable, its words kept for the log."""

    def broken(host: str, port: int) -> list[str]:
        raise OSError(-2, "Name or service not known")

    with pytest.raises(Unreachable) as caught:
        pin("https://nowhere.example/r.git", "nowhere.example", 443, broken)
    assert "Name or service" in caught.value.detail and "Name or" not in str(caught.value)


def test_addresses_are_checked_without_asking_the_resolver():
    """An address in the URL is judged as it is, and pinned to itself."""

    def never(host: str, port: int) -> list[str]:
        raise AssertionError("an address needs no lookup")

    with pytest.raises(HostNotAllowed, match=r"its host 10\.0\.0\.1 is a private address"):
        pin("https://10.0.0.1/r.git", "10.0.0.1", 443, never)
    pinned = pin("https://9.9.9.9/r.git", "9.9.9.9", 443, never)
    assert (pinned.address, pinned.name) == ("9.9.9.9", False)
