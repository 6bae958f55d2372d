"""The OpenID providers of ``labd serve``: one from flags (its secret from the flag, the
variable or the file's [serve]), several from the file's [oidc.NAME] tables, and the
sign-up rule; a wrong one is refused in a sentence that says where."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from labd.cli import main
from labd.commands import serve
from labd.commands.serve import Refused
from labd.oidc import OidcConfig, Provider
from tests.labd.test_settings import configured, write


def oidc_of(argv: list[str], environ: dict[str, str] | None = None) -> OidcConfig:
    args, _ = configured(["serve", *argv], environ)
    return serve.oidc_config(args)


def test_one_provider_from_flags_its_secret_from_the_variable():
    found = oidc_of(
        ["--oidc-issuer", "https://accounts.google.com", "--oidc-client-id", "labd.apps"],
        {"LABD_OIDC_CLIENT_SECRET": "from-env"},
    )
    assert found.providers == (
        Provider("accounts-google-com", "https://accounts.google.com", "labd.apps", "from-env"),
    )
    assert found.providers[0].shown == "accounts.google.com"


def test_several_providers_from_the_file(tmp_path: Path):
    write(tmp_path / "university.secret", "from-a-file\n")
    lab = write(
        tmp_path / "labd.toml",
        '[serve]\noidc_allow_domain = ["example.edu"]\n'
        '[oidc.university]\nissuer = "https://login.example.edu/realms/staff"\n'
        'client_id = "labd"\nclient_secret_file = "university.secret"\n'
        'title = "Example University"\n'
        '[oidc.gitlab]\nissuer = "https://gitlab.example.org"\nclient_id = "abc"\n',
    )
    found = oidc_of(["--config", str(lab)])
    university, gitlab = found.providers
    assert university == Provider(
        "university",
        "https://login.example.edu/realms/staff",
        "labd",
        "from-a-file",
        "Example University",
    )
    assert university.metadata_url == (
        "https://login.example.edu/realms/staff/.well-known/openid-configuration"
    )
    assert (gitlab.name, gitlab.client_secret, gitlab.shown) == ("gitlab", "", "gitlab.example.org")
    assert found.domains == ("example.edu",)


@pytest.mark.parametrize(
    ("argv", "toml", "said"),
    [
        (["--oidc-issuer", "https://a.test"], "", "--oidc-issuer and --oidc-client-id go together"),
        (
            ["--oidc-issuer", "http://login.example.org", "--oidc-client-id", "x"],
            "",
            "an issuer is an https:// address",
        ),
        ([], '[oidc.Big]\nissuer = "https://a.test"\nclient_id = "x"\n', "lowercase"),
        ([], '[oidc.callback]\nissuer = "https://a.test"\nclient_id = "x"\n', "not 'callback'"),
        ([], '[oidc.a]\nissuer = "https://a.test"\n', "[oidc.a] needs client_id"),
        ([], '[oidc.a]\nissuer = "https://a.test"\nclient_id = "x"\nsecret = "s"\n', "secret:"),
        (
            [],
            '[oidc.a]\nissuer = "https://a.test"\nclient_id = "x"\nclient_secret_file = "nope"\n',
            "No such file",
        ),
        (["--oidc-allow-domain", "example.edu"], "", "need an OpenID provider"),
    ],
)
def test_a_provider_configured_wrongly_is_refused_saying_how(tmp_path, argv, toml, said):
    lab = write(tmp_path / "labd.toml", toml)
    with pytest.raises(Refused) as caught:
        oidc_of(["--config", str(lab), *argv])
    assert said in str(caught.value)


@pytest.mark.parametrize(
    ("claims", "refused"),
    [
        ({"email": "ann@example.edu", "email_verified": True}, False),
        ({"email": "Bob@Gmail.test", "email_verified": True}, False),
        ({"email": "ann@example.edu"}, True),
        ({"email": "eve@evil.test", "email_verified": True}, True),
        ({}, True),
    ],
)
def test_who_may_sign_up(claims, refused):
    config = OidcConfig((), ("example.edu",), ("bob@gmail.test",))
    assert bool(config.refusal(claims)) is refused
    assert OidcConfig().refusal(claims) == ""  # by default anyone may


def test_the_operator_links_a_provider_s_person_to_an_account(tmp_path, capsys):
    """``labd users link`` lets a person an OpenID provider vouches for sign in to an
    account the operator made; ``labd users list`` says so; one provider account signs
    in to one lab account only."""
    data = ["--data", str(tmp_path / "lab")]
    assert main(["users", "add", "carol", *data]) == 0
    assert main(["users", "add", "dave", *data]) == 0
    capsys.readouterr()
    link = ["--issuer", "https://sso.example.edu", "--subject", "s-9", "--email", "c@x.edu"]
    assert main(["users", "link", "carol", *link, *data]) == 0
    assert (
        capsys.readouterr().out
        == "carol: s-9 of https://sso.example.edu signs in to this account\n"
    )
    assert main(["users", "list", "--json", *data]) == 0
    carol = next(u for u in json.loads(capsys.readouterr().out) if u["name"] == "carol")
    assert carol["identities"] == [
        {"issuer": "https://sso.example.edu", "subject": "s-9", "email": "c@x.edu"}
    ]
    assert main(["users", "link", "dave", *link, *data]) == 2  # refused, as any bad input
    assert "signs in to another account of this lab already" in capsys.readouterr().err
