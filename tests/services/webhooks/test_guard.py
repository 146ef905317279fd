"""Where webhooks may go (`HostGuard`): listed hosts only; never this depot's own ports on this
machine nor link-local or metadata addresses, by whatever name, unless that very HOST:PORT is listed."""

from __future__ import annotations

import pytest

from services.webhooks.guard import HostGuard, RefusedUrlError

DEPOT_PORTS = [8080, 51234]
DNS = {
    "hooks.example": ["203.0.113.7"],
    "metadata.example": ["169.254.169.254"],
    "sneaky.example": ["203.0.113.8", "169.254.169.254"],  # one bad address of several is enough
    "v6-metadata.example": ["fd00:ec2::254"],
    "mapped.example": ["::ffff:169.254.169.254"],
    "localhost": ["127.0.0.1", "::1"],
    "v6.example": ["2001:db8::1"],
}


def resolver(host: str, port: int) -> list[str]:
    if host in DNS:
        return DNS[host]
    if host.replace(".", "").isdigit() or ":" in host:  # an address resolves to itself
        return [host]
    raise OSError("Name or service not known")


def guard(*allowed: str) -> HostGuard:
    return HostGuard(allowed, DEPOT_PORTS, resolver=resolver)


def refused(guard: HostGuard, url: str, *says: str) -> None:
    with pytest.raises(RefusedUrlError) as info:
        guard.check(url)
    assert info.value.http_status() == 422
    for text in says:
        assert text in info.value.message, info.value.message


def test_with_no_host_listed_nothing_is_allowed_and_the_answer_says_what_to_set():
    refused(guard(), "https://hooks.example/x", "no webhook host is allowed", "FLEET_WEBHOOK_HOSTS=hooks.example")


def test_a_listed_host_is_allowed_on_any_port_and_a_listed_host_port_on_that_port_only():
    allowed = guard("hooks.example", "127.0.0.1:9000")
    target = allowed.check("https://hooks.example/services/a?b=1")
    assert (target.host, target.port, target.address) == ("hooks.example", 443, "203.0.113.7")
    assert target.connect_url == "https://203.0.113.7:443/services/a?b=1"
    assert target.host_header == "hooks.example"
    assert allowed.check("http://HOOKS.example:8443").host_header == "hooks.example:8443"
    assert allowed.check("http://127.0.0.1:9000/").connect_url == "http://127.0.0.1:9000/"
    refused(allowed, "http://127.0.0.1:9001/", "127.0.0.1:9001 is not in FLEET_WEBHOOK_HOSTS")
    refused(allowed, "https://other.example/", "other.example:443 is not in FLEET_WEBHOOK_HOSTS")


@pytest.mark.parametrize(
    ("url", "address"),
    [
        ("http://169.254.169.254/latest/meta-data/", "169.254.169.254"),
        ("http://metadata.example/", "169.254.169.254"),
        ("http://sneaky.example/", "169.254.169.254"),
        ("http://v6-metadata.example/", "fd00:ec2::254"),
        ("http://mapped.example/", "169.254.169.254"),
        ("http://[fe80::1]/", "fe80::1"),
        ("http://0.0.0.0:9000/", "0.0.0.0"),
    ],
)
def test_link_local_and_metadata_addresses_are_refused_by_any_name(url: str, address: str):
    hosts = ("169.254.169.254", "metadata.example", "sneaky.example", "v6-metadata.example", "mapped.example")
    refused(guard(*hosts, "fe80::1", "0.0.0.0"), url, address, "link-local or metadata address")


def test_the_depots_own_ports_on_this_machine_are_refused_other_loopback_ports_are_not():
    local = guard("localhost", "127.0.0.1", "::1")
    refused(local, "http://localhost:8080/v1/tokens", "this depot's own port")
    refused(local, "http://127.0.0.1:51234/", "this depot's own port")
    refused(local, "http://[::1]:8080/", "this depot's own port")
    assert local.check("http://localhost:9000/hook").address == "127.0.0.1"


def test_only_the_very_host_port_listed_lets_an_admin_allow_what_is_refused_otherwise():
    assert guard("127.0.0.1:8080").check("http://127.0.0.1:8080/").port == 8080
    assert guard("metadata.example:80").check("http://metadata.example/").address == "169.254.169.254"
    refused(guard("metadata.example:81"), "http://metadata.example/", "not in FLEET_WEBHOOK_HOSTS")


def test_ipv6_targets_keep_their_brackets():
    target = guard("v6.example", "[2001:db8::2]:9000").check("http://v6.example:9000/h")
    assert (target.connect_url, target.host_header) == ("http://[2001:db8::1]:9000/h", "v6.example:9000")
    assert guard("[2001:db8::2]:9000").check("http://[2001:db8::2]:9000/").host_header == "[2001:db8::2]:9000"


@pytest.mark.parametrize(
    ("url", "says"),
    [
        ("ftp://hooks.example/", "starts with http:// or https://"),
        ("hooks.example/x", "starts with http:// or https://"),
        ("https://user:pass@hooks.example/", "no user or password"),
        ("https:///path", "names no host"),
        ("https://hooks.example:99999/", "is not a URL"),
        ("https://hooks.example/a b", "no spaces"),
        ("https://hooks.example/#frag", "no #fragment"),
        ("https://hooks.example/" + "a" * 3000, "at most 2048 characters"),
        ("https://nowhere.example/", "not in FLEET_WEBHOOK_HOSTS"),
    ],
)
def test_what_is_no_plain_http_url_is_refused(url: str, says: str):
    refused(guard("hooks.example"), url, says)


def test_a_listed_host_that_does_not_resolve_is_refused():
    refused(guard("nowhere.example"), "https://nowhere.example/", "does not resolve")
