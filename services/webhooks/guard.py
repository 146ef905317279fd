"""Where webhooks may be sent: only to hosts an admin listed (FLEET_WEBHOOK_HOSTS), and never, by a
name that resolves there, to this depot's own ports on this machine or to link-local and cloud
metadata addresses, unless the admin listed that very HOST:PORT.

A URL is checked when a webhook is added and again before each delivery: its host is resolved and
every address checked, and the delivery connects to the address checked (not to a name resolved
again), so a name that changes its answer in between reaches nothing it was refused."""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import cached_property
from urllib.parse import urlsplit, urlunsplit

from core.errors import InvalidArgumentError

Address = ipaddress.IPv4Address | ipaddress.IPv6Address
Resolver = Callable[[str, int], list[str]]
MAX_URL_LENGTH = 2048
DEFAULT_PORTS = {"http": 80, "https": 443}

# Addresses that are never a webhook's: link-local (where clouds answer metadata queries), the
# metadata services' own addresses, and addresses that are no single host.
FORBIDDEN_NETWORKS = tuple(
    ipaddress.ip_network(n)
    for n in (
        "169.254.0.0/16",  # link-local; 169.254.169.254 is the metadata service of most clouds
        "fe80::/10",  # link-local
        "fd00:ec2::254/128",  # AWS metadata over IPv6
        "100.100.100.200/32",  # Alibaba Cloud metadata
        "0.0.0.0/8",  # "this host": reaches loopback on most systems
        "::/128",
        "224.0.0.0/4",  # multicast
        "ff00::/8",
        "255.255.255.255/32",
    )
)


class RefusedUrlError(InvalidArgumentError):
    """A webhook URL this depot will not send to, and why."""


@dataclass(frozen=True)
class Target:
    """A checked URL and the address a delivery connects to."""

    url: str  # as given
    host: str
    port: int
    address: str  # the checked address to connect to
    connect_url: str  # the URL with the address in place of the host
    host_header: str  # the Host header (the URL's host, and its port unless the default)


def resolve(host: str, port: int) -> list[str]:
    """The addresses `host` resolves to (the system's resolver)."""
    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    return list(dict.fromkeys(str(info[4][0]) for info in infos))


class HostGuard:
    """The allow-list (`allowed`: HOST or HOST:PORT entries) and the depot's own ports."""

    def __init__(self, allowed: Iterable[str], own_ports: Iterable[int], resolver: Resolver = resolve) -> None:
        self.hosts: set[str] = set()
        self.exact: set[tuple[str, int]] = set()
        for entry in allowed:
            host, port = _split_entry(entry)
            if port is None:
                self.hosts.add(host)
            else:
                self.exact.add((host, port))
        self.own_ports = frozenset(p for p in own_ports if p)
        self.resolver = resolver

    def check(self, url: str) -> Target:
        """The target of `url` if this depot may send to it, else RefusedUrlError saying why."""
        scheme, host, port, parts = _parse(url)
        exact = (host, port) in self.exact
        if not exact and host not in self.hosts:
            raise RefusedUrlError(self._not_listed(host, port))
        try:
            addresses = self.resolver(host, port)
        except (OSError, UnicodeError) as exc:
            raise RefusedUrlError(f"webhook host {host!r} does not resolve ({exc})") from None
        if not addresses:
            raise RefusedUrlError(f"webhook host {host!r} does not resolve")
        if not exact:
            for address in addresses:
                self._check_address(host, port, address)
        address = addresses[0]
        shown = f"[{address}]" if ":" in address else address
        connect_url = urlunsplit((scheme, f"{shown}:{port}", parts[0] or "/", parts[1], ""))
        named = f"[{host}]" if ":" in host else host
        host_header = named if port == DEFAULT_PORTS[scheme] else f"{named}:{port}"
        return Target(url, host, port, address, connect_url, host_header)

    def _not_listed(self, host: str, port: int) -> str:
        if not self.hosts and not self.exact:
            return (
                "no webhook host is allowed on this depot: an admin lists the hosts webhooks may reach in "
                f"FLEET_WEBHOOK_HOSTS (e.g. FLEET_WEBHOOK_HOSTS={host} or {host}:{port})"
            )
        return f"webhook host {host}:{port} is not in FLEET_WEBHOOK_HOSTS (an admin adds {host} or {host}:{port} there)"

    def _check_address(self, host: str, port: int, text: str) -> None:
        address = _address(text)
        if any(address in network for network in FORBIDDEN_NETWORKS):
            raise RefusedUrlError(
                f"webhook host {host} resolves to {address}, a link-local or metadata address: refused "
                f"(only an admin listing {host}:{port} itself in FLEET_WEBHOOK_HOSTS allows it)"
            )
        if port in self.own_ports and (address.is_loopback or address in self._this_host):
            raise RefusedUrlError(
                f"webhook URL {host}:{port} is this depot's own port ({address}): refused "
                f"(only an admin listing {host}:{port} itself in FLEET_WEBHOOK_HOSTS allows it)"
            )

    @cached_property
    def _this_host(self) -> frozenset[Address]:
        """This machine's own addresses, as its name resolves."""
        try:
            return frozenset(_address(a) for a in resolve(socket.gethostname(), 0))
        except (OSError, UnicodeError, ValueError):
            return frozenset()


def _address(text: str) -> Address:
    address = ipaddress.ip_address(text.split("%", 1)[0])  # a scope (fe80::1%eth0) is no part of it
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return address.ipv4_mapped  # ::ffff:169.254.169.254 is 169.254.169.254
    return address


def _parse(url: str) -> tuple[str, str, int, tuple[str, str]]:
    """Scheme, host (lowercase, no brackets), port (the scheme's default if none) and path and
    query of a webhook URL; RefusedUrlError for anything that is no plain http(s) URL."""
    if len(url) > MAX_URL_LENGTH or any(c.isspace() or ord(c) < 32 or 0xD800 <= ord(c) < 0xE000 for c in url):
        raise RefusedUrlError(
            f"a webhook URL is an http(s) URL of at most {MAX_URL_LENGTH} characters, "
            "no spaces, control characters or unpaired surrogates"
        )
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise RefusedUrlError(f"{url!r} is not a URL ({exc})") from None
    if parts.scheme not in DEFAULT_PORTS:
        raise RefusedUrlError(f"a webhook URL starts with http:// or https://, not {parts.scheme or 'nothing'}")
    if parts.username is not None or parts.password is not None:
        raise RefusedUrlError("a webhook URL carries no user or password: deliveries are signed instead")
    if not parts.hostname:
        raise RefusedUrlError(f"{url!r} names no host")
    if parts.fragment:
        raise RefusedUrlError("a webhook URL has no #fragment")
    return parts.scheme, parts.hostname.lower(), port or DEFAULT_PORTS[parts.scheme], (parts.path, parts.query)


def _split_entry(entry: str) -> tuple[str, int | None]:
    """`host`, `host:port`, `[v6]:port` or a bare IPv6 address, as FLEET_WEBHOOK_HOSTS lists them."""
    text = entry.strip().lower()
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        return host, int(rest[1:]) if rest.startswith(":") and rest[1:].isdigit() else None
    if text.count(":") == 1:
        host, port = text.split(":")
        if port.isdigit():
            return host, int(port)
    return text, None
