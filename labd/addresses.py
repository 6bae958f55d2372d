"""Clients by address, as the lab's servers count them to share their connections out.

One client machine is one address: an IPv4 address (an IPv4-mapped IPv6 address is
its IPv4 address), or an IPv6 /64, the block a single site is usually given, so that
one machine cannot pose as many by changing the low bits of its address. A connection
with no IP address (a unix socket: a trial's private bridge) belongs to no address and
is never counted.
"""

from __future__ import annotations

import ipaddress
from collections import Counter
from typing import Any

IPV6_SITE = 64  # prefix length of the IPv6 block counted as one address


def address_of(peer: Any) -> str | None:
    """The address ``peer`` (a socket's ``getpeername()``) is counted under, or None."""
    if not isinstance(peer, tuple) or not peer or not isinstance(peer[0], str):
        return None
    try:
        ip = ipaddress.ip_address(peer[0].split("%", 1)[0])
    except ValueError:
        return None
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, IPV6_SITE), strict=False))
    return str(ip)


class PerAddress:
    """How many connections each address holds, against a limit for each (0: none).

    ``take`` counts a connection in if its address is under the limit; ``give`` counts
    it out. Addresses holding nothing are forgotten, so the table stays as small as the
    set of clients connected now.
    """

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held: Counter[str] = Counter()

    def held(self, address: str | None) -> int:
        return 0 if address is None else self._held[address]

    def full(self, address: str | None) -> bool:
        """Whether ``address`` holds its limit (never, for no address or no limit)."""
        return address is not None and self.limit > 0 and self._held[address] >= self.limit

    def take(self, address: str | None) -> bool:
        """Count a connection of ``address`` in, unless it holds its limit already."""
        if self.full(address):
            return False
        if address is not None:
            self._held[address] += 1
        return True

    def give(self, address: str | None) -> None:
        """Count a connection of ``address`` out."""
        if address is None or address not in self._held:
            return
        self._held[address] -= 1
        if self._held[address] <= 0:
            del self._held[address]
