"""Clients by address: what one address is, and counting connections under it."""

from __future__ import annotations

import pytest

from labd.addresses import PerAddress, address_of


@pytest.mark.parametrize(
    ("peer", "address"),
    [
        (("127.0.0.1", 5000), "127.0.0.1"),
        (("::ffff:10.0.0.7", 5000, 0, 0), "10.0.0.7"),  # IPv4-mapped: its IPv4 address
        (("2001:db8:1:2:aaaa::1", 5000, 0, 0), "2001:db8:1:2::/64"),
        (("2001:db8:1:2:ffff::9", 5000, 0, 0), "2001:db8:1:2::/64"),  # the same site
        (("fe80::1%eth0", 5000, 0, 2), "fe80::/64"),
        ("", None),  # a unix socket's peer
        (None, None),
        (("not an address", 1), None),
    ],
)
def test_an_address_is_an_ipv4_address_or_an_ipv6_site(peer, address):
    """IPv4 counts per address, IPv6 per /64, and a unix socket under no address."""
    assert address_of(peer) == address


def test_an_address_holds_at_most_its_limit():
    """Past its limit an address is refused until one of its connections goes; others
    and connections without an address are not affected."""
    held = PerAddress(2)
    assert held.take("a") and held.take("a")
    assert not held.take("a") and held.full("a")
    assert held.take("b")
    assert all(held.take(None) for _ in range(10))
    held.give("a")
    assert held.take("a") and held.held("a") == 2
    held.give("b")
    assert held.held("b") == 0


def test_no_limit_counts_without_refusing():
    """A limit of 0 refuses no one."""
    held = PerAddress(0)
    assert all(held.take("a") for _ in range(1000))
    assert held.held("a") == 1000 and not held.full("a")
