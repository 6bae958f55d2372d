"""Signing in through OpenID Connect providers: who they are, and who may sign up.

An operator names one provider with flags (``labd serve --oidc-issuer URL
--oidc-client-id ID``, the secret in ``--oidc-client-secret``, ``LABD_OIDC_CLIENT_SECRET``
or the configuration file) or several in the configuration file, a table each:

    [oidc.university]
    issuer = "https://login.example.edu/realms/staff"
    client_id = "labd"
    client_secret = "..."          # or client_secret_file = "/etc/labd/university.secret"
    title = "Example University"   # "Sign in with Example University"

The pages (``labd.web.oidc``) do the redirect flow; this module decides what a verified
ID token's claims make of a person: the account its (issuer, subject) signs in to, or a
new one, if the operator lets them sign up (anyone, by default; or only verified e-mail
addresses in ``--oidc-allow-domain`` domains, or ``--oidc-invite`` addresses).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from labd.errors import LabError

NAME = re.compile(r"[a-z0-9][a-z0-9-]{0,31}")
SCOPES = "openid email profile"


class OidcConfigError(LabError):
    """An OpenID provider configured wrongly: the sentence says which and how."""


@dataclass(frozen=True)
class Provider:
    """One OpenID provider the lab signs people in through."""

    name: str  # in the address: /session/oidc/NAME
    issuer: str  # its discovery document is ISSUER/.well-known/openid-configuration
    client_id: str
    client_secret: str = ""  # none: a public client (PKCE alone)
    title: str = ""  # "Sign in with TITLE"; by default the issuer's host

    @property
    def shown(self) -> str:
        return self.title or urlsplit(self.issuer).hostname or self.name

    @property
    def metadata_url(self) -> str:
        return self.issuer.rstrip("/") + "/.well-known/openid-configuration"


@dataclass(frozen=True)
class OidcConfig:
    """The providers, and who may make an account by signing in."""

    providers: tuple[Provider, ...] = ()
    domains: tuple[str, ...] = ()  # a verified e-mail in one of these may sign up
    invited: tuple[str, ...] = ()  # and these addresses, whatever their domain

    def provider(self, name: str) -> Provider | None:
        return next((p for p in self.providers if p.name == name), None)

    def refusal(self, claims: Mapping[str, Any]) -> str:
        """Why the person of ``claims`` may not make an account here ("" if they may)."""
        if not self.domains and not self.invited:
            return ""
        email = str(claims.get("email") or "").strip().lower()
        if not email or claims.get("email_verified") is not True:
            return (
                "this lab makes accounts only for people with a verified e-mail address"
                " it knows, and your provider vouched for none"
            )
        domain = email.rpartition("@")[2]
        if email in self.invited or domain in self.domains:
            return ""
        return (
            f"this lab makes accounts only for {_whom(self.domains)}: ask its operator"
            " for an invitation"
        )


def _whom(domains: tuple[str, ...]) -> str:
    if not domains:
        return "people it invited"
    listed = ", ".join(f"@{d}" for d in domains)
    return f"addresses at {listed} and people it invited"


def wanted_name(claims: Mapping[str, Any]) -> str:
    """What a new account would be called: the provider's ``preferred_username``, else
    the e-mail's local part, else its subject (``repository.accounts.usable_name`` makes
    it a valid and unique name)."""
    for value in (claims.get("preferred_username"), str(claims.get("email") or "").split("@")[0]):
        if isinstance(value, str) and value.strip():
            return value.strip()
    return str(claims.get("sub", "user"))


# -- from the command line and the configuration file --------------------------------------


def configured(args: argparse.Namespace, document: Mapping[str, Any]) -> OidcConfig:
    """The providers of ``labd serve``'s flags and of the file's ``[oidc.NAME]`` tables."""
    providers: list[Provider] = []
    if args.oidc_issuer or args.oidc_client_id:
        if not (args.oidc_issuer and args.oidc_client_id):
            raise OidcConfigError("--oidc-issuer and --oidc-client-id go together")
        title = args.oidc_name or ""
        name = _slug(title or urlsplit(args.oidc_issuer).hostname or "oidc")
        providers.append(
            _checked(Provider(name, args.oidc_issuer, args.oidc_client_id,
                              args.oidc_client_secret or "", title), "--oidc-issuer")
        )  # fmt: skip
    tables = document.get("oidc", {})
    if not isinstance(tables, dict):
        raise OidcConfigError("[oidc] must hold a table per provider: [oidc.NAME]")
    base = Path(args.config).parent if getattr(args, "config", None) else Path()
    for name, table in tables.items():
        providers.append(_from_table(name, table, base))
    names = [p.name for p in providers]
    if len(set(names)) != len(names):
        raise OidcConfigError(f"two OpenID providers are called the same: {', '.join(names)}")
    domains = tuple(d.strip().lower().lstrip("@") for d in args.oidc_allow_domain)
    invited = tuple(e.strip().lower() for e in args.oidc_invite)
    if (domains or invited) and not providers:
        raise OidcConfigError("--oidc-allow-domain and --oidc-invite need an OpenID provider")
    return OidcConfig(tuple(providers), domains, invited)


KEYS = frozenset({"issuer", "client_id", "client_secret", "client_secret_file", "title"})


def _from_table(name: str, table: Any, base: Path) -> Provider:
    where = f"[oidc.{name}]"
    if not isinstance(table, dict):
        raise OidcConfigError(f"{where} must be a table")
    unknown = sorted(set(table) - KEYS)
    if unknown:
        known = ", ".join(sorted(KEYS))
        raise OidcConfigError(f"{where}: {', '.join(unknown)}: not one of {known}")
    for key in ("issuer", "client_id"):
        if not isinstance(table.get(key), str) or not table[key]:
            raise OidcConfigError(f"{where} needs {key} (a string)")
    secret = table.get("client_secret", "")
    if "client_secret_file" in table:
        path = base / str(table["client_secret_file"])
        try:
            secret = path.read_text().strip()
        except OSError as err:
            raise OidcConfigError(f"{where} client_secret_file {path}: {err.strerror}") from None
    provider = Provider(name, table["issuer"], table["client_id"], str(secret),
                        str(table.get("title", "")))  # fmt: skip
    return _checked(provider, where)


def _checked(provider: Provider, where: str) -> Provider:
    if NAME.fullmatch(provider.name) is None or provider.name == "callback":
        raise OidcConfigError(
            f"{where}: the name {provider.name!r} goes in addresses: use up to 32 lowercase"
            " letters, digits and '-' (and not 'callback')"
        )
    parts = urlsplit(provider.issuer)
    local = parts.hostname in ("127.0.0.1", "localhost", "::1")
    if parts.scheme != "https" and not (parts.scheme == "http" and local):
        raise OidcConfigError(
            f"{where} {provider.issuer}: an issuer is an https:// address (http:// only on"
            " this machine, for tests)"
        )
    return provider


def _slug(text: str) -> str:
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")[:32].strip("-")
    return slug or "oidc"
