"""Which hosts a lab fetches repositories from: public addresses only, unless its operator
allows private ones (``FetchPolicy.private_hosts``, ``--allow-private-hosts``).

A submission names a URL, and the lab's git connects to it: from the lab's machine, on
the lab's network. Without this check a submitter reaches what only the lab reaches (its
loopback ports, its LAN, the cloud's metadata service at 169.254.169.254) and, by how
the fetch fails, tells a closed port from an open one. So before git runs:

- the host of an http(s), git or ssh URL (``user@host:path`` included) is looked up, and
  every address the name resolves to must be public (``kind``: loopback, link-local,
  private, unspecified, multicast, reserved and the other non-global ranges are not;
  an IPv6 address that embeds an IPv4 one, mapped, 6to4 or NAT64, is judged by that);
- git then connects to the very address that was checked (``Pinned``), never resolving
  the name again: a name whose answer changes between the check and the connection
  (DNS rebinding, a TTL of 0) cannot slip a private address in. ``scheduler.fetch`` pins
  it for curl (``http.curloptResolve``), for ssh (``HostName``, with the name kept for
  the host key), and for git's own protocol by putting the address in the URL git is
  given (the URL the lab records keeps the name). Redirects are not followed then: a
  public server could otherwise send git to a private one.

``kind`` is a pure function of an address; ``pin`` takes the resolver as an argument
(``lookup``), so both are tested without a network.
"""

from __future__ import annotations

import ipaddress
import re
import socket
from collections.abc import Callable
from dataclasses import dataclass
from urllib.parse import urlsplit

from scheduler.errors import HostNotAllowed, RepositoryError, Unreachable

Address = ipaddress.IPv4Address | ipaddress.IPv6Address
Lookup = Callable[[str, int], list[str]]
PORTS = {"http": 80, "https": 443, "git": 9418, "ssh": 22}
SCP = re.compile(r"^(?:[^@/\s]+@)?(\[[0-9A-Fa-f:.]+\]|[\w.-]+):")  # user@host:path
NAT64 = ipaddress.IPv6Network("64:ff9b::/96")  # RFC 6052: the last 32 bits are IPv4


@dataclass(frozen=True)
class Pinned:
    """The addresses git connects to for ``host:port``, each checked to be public, the
    first first. ``name``: the host is a name (its addresses are pinned), not an
    address given in the URL; ``host`` is then as the resolver takes it (IDNA)."""

    host: str
    port: int
    addresses: tuple[str, ...]
    name: bool

    @property
    def address(self) -> str:
        """The first address: the one where only one can be given (ssh, git://)."""
        return self.addresses[0]

    @property
    def bracketed(self) -> str:
        """The first address as a URL writes it (an IPv6 one in brackets)."""
        return _bracketed(self.address)

    @property
    def resolve(self) -> str:
        """curl's ``HOST:PORT:ADDRESS[,ADDRESS]``: every address, so that curl may fall
        back from one it cannot reach (IPv6 on a machine without a route) to the next."""
        return f"{self.host}:{self.port}:{','.join(map(_bracketed, self.addresses))}"


def kind(address: Address) -> str | None:
    """What makes ``address`` no public one, in a word a person understands; None for
    a public address."""
    if isinstance(address, ipaddress.IPv6Address):
        embedded = address.ipv4_mapped or address.sixtofour
        if embedded is None and address in NAT64:
            embedded = ipaddress.IPv4Address(int(address) & 0xFFFFFFFF)
        if embedded is not None:
            return kind(embedded)
        if address.is_site_local:
            return "site-local"
    for word, found in (
        ("unspecified", address.is_unspecified),
        ("loopback", address.is_loopback),
        ("link-local", address.is_link_local),
        ("multicast", address.is_multicast),
        ("private", address.is_private),
        ("reserved", address.is_reserved),
        ("non-public", not address.is_global),  # shared (100.64.0.0/10) and the like
    ):
        if found:
            return word
    return None


def endpoint(url: str, scheme: str) -> tuple[str, int] | None:
    """The host and port a repository's URL connects to (None for a local one, or one
    with no host). ``user@host:path`` is ssh's, on its port 22."""
    if scheme == "file":
        return None
    if "://" not in url:
        scp = SCP.match(url)
        return (scp.group(1).strip("[]"), PORTS["ssh"]) if scp else None
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        raise RepositoryError(url, "is not a valid URL") from None
    if not parts.hostname:
        return None
    return parts.hostname, port or PORTS.get(scheme, 0)


def literal(host: str) -> Address | None:
    """``host`` as an address, when it is one (``127.1`` and ``0x7f.1`` included, as the
    C resolver reads them); None for a name."""
    try:
        return ipaddress.ip_address(host)
    except ValueError:
        pass
    try:  # inet_aton's forms: what git would connect to for such a "name"
        return ipaddress.IPv4Address(socket.inet_aton(host))
    except OSError:
        return None


def pin(source: str, host: str, port: int, lookup: Lookup | None = None) -> Pinned:
    """The public address to fetch ``source`` from, at ``host:port``.

    ``HostNotAllowed`` when the host, or any address its name resolves to, is not
    public; ``Unreachable`` when the name resolves to nothing (said as every network
    failure is). ``lookup`` resolves a name (default: the system's resolver).
    """
    given = literal(host)
    if given is not None:
        found = kind(given)
        if found is not None:
            raise HostNotAllowed(source, host, found)
        return Pinned(host, port, (str(given),), name=False)
    try:
        host = host.encode("idna").decode("ascii")  # as the resolver, and curl, take it
        addresses = (lookup or resolve_name)(host, port)
    except (OSError, UnicodeError) as err:
        raise Unreachable(source, f"{host} does not resolve: {err}") from None
    if not addresses:
        raise Unreachable(source, f"{host} resolves to no address")
    checked = [ipaddress.ip_address(a.partition("%")[0]) for a in addresses]
    for address in checked:
        found = kind(address)
        if found is not None:
            raise HostNotAllowed(source, host, found, name=True)
    return Pinned(host, port, tuple(map(str, checked)), name=True)


def _bracketed(address: str) -> str:
    return f"[{address}]" if ":" in address else address


def resolve_name(host: str, port: int) -> list[str]:
    """Every address ``host`` resolves to for a TCP connection (the system's resolver,
    as git's own would ask it)."""
    found = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return list(dict.fromkeys(str(info[4][0]) for info in found))
