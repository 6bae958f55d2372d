"""Signing in through OpenID Connect against a real provider on 127.0.0.1.

The provider is ``oidc-provider-mock`` (an OpenID provider made with Authlib and
Flask, run here on a thread): its authorization page asks which subject signs in, and
``PUT /users/SUB`` sets that person's claims. A lab configured with it as issuer is
driven through the whole redirect flow by an HTTP client that keeps cookies as a
browser does (``tests/integration/test_oidc_browser.py`` does it in Chromium): to the
provider with state, nonce and PKCE; back to the callback with a code; the lab's own
session after. The tokens an untrustworthy provider would send (another audience,
another issuer, expired) are made by a proxy in front of the provider that re-signs
its ID token with the provider's own key, so only the claim under test is wrong.
"""

from __future__ import annotations

import base64
import contextlib
import json
import threading
from collections.abc import Callable, Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

import httpx
import pytest
import sqlalchemy as sa
import werkzeug.serving

from labd.oidc import OidcConfig, Provider
from repository.tables import identities
from tests.helpers.labs import lab_config, running

oidc_provider_mock = pytest.importorskip("oidc_provider_mock")

pytestmark = [pytest.mark.integration, pytest.mark.timeout(120)]
CLIENT = "labd-test"
WSGI = Callable[[dict[str, Any], Callable[..., Any]], Any]


@contextlib.contextmanager
def provider(app: WSGI) -> Iterator[str]:
    """Serve ``app`` on 127.0.0.1 on a thread; its issuer URL."""
    server = werkzeug.serving.make_server("127.0.0.1", 0, app, threaded=True)
    thread = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_port}"
    finally:
        server.shutdown()
        thread.join(10)
        server.server_close()


@contextlib.contextmanager
def lab_with(tmp_path: Path, issuer: str, **oidc: Any) -> Iterator[Any]:
    config = OidcConfig((Provider("test", issuer, CLIENT, "shh", "Test University"),), **oidc)
    with running(lab_config(tmp_path / "data", robots=(), service={"oidc": config})) as server:
        yield server


class Person:
    """Someone with a browser: an HTTP client that keeps cookies and follows nothing
    by itself, so each leg of the flow is seen."""

    def __init__(self, lab: Any, issuer: str) -> None:
        self.lab = lab
        self.issuer = issuer
        self.http = httpx.Client(timeout=30)
        BROWSERS.append(self.http)

    def set_claims(self, subject: str, **claims: Any) -> None:
        reply = self.http.put(f"{self.issuer}/users/{subject}", json=claims)
        assert reply.status_code == 204, reply.text

    def start(self, then: str = "/tokens") -> str:
        """To the lab's sign-in, then to the provider: the authorization URL."""
        reply = self.http.get(self.lab.http_url(f"/session/oidc?then={then}"))
        assert reply.status_code in (302, 303), reply.text
        where = reply.headers["location"]
        assert where.startswith(f"{self.issuer}/oauth2/authorize?")
        return str(where)

    def authorize(self, url: str, subject: str) -> str:
        """The provider's page, answered as ``subject``: the lab's callback URL."""
        assert self.http.get(url).status_code == 200
        reply = self.http.post(url, data={"sub": subject})
        assert reply.status_code == 302, reply.text
        return str(reply.headers["location"])

    def sign_in(self, subject: str, then: str = "/tokens") -> httpx.Response:
        return self.http.get(self.authorize(self.start(then), subject))

    def me(self) -> httpx.Response:
        return self.http.get(self.lab.http_url("/api/me"))


BROWSERS: list[httpx.Client] = []


@pytest.fixture(autouse=True)
def _closed_browsers() -> Iterator[None]:
    yield
    while BROWSERS:
        BROWSERS.pop().close()


@pytest.fixture
def issuer() -> Iterator[str]:
    with provider(oidc_provider_mock.app()) as url:
        yield url


def test_a_person_signs_in_through_the_whole_flow_and_again_to_the_same_account(tmp_path, issuer):
    """The lab sends the person to the provider (code flow, S256 PKCE, state and
    nonce); back at the callback it makes their account, named after their preferred
    username, and signs them in with its own session, which /api/me answers for. A
    second sign-in, in another browser, reaches the same account; so does one after the
    provider changed their e-mail: the account is keyed by issuer and subject."""
    with lab_with(tmp_path, issuer) as lab:
        ann = Person(lab, issuer)
        ann.set_claims("s-ann", email="ann@example.edu", email_verified=True,
                       preferred_username="ann")  # fmt: skip
        authorize = parse_qs(urlsplit(ann.start()).query)
        assert authorize["response_type"] == ["code"]
        assert authorize["client_id"] == [CLIENT]
        assert authorize["code_challenge_method"] == ["S256"]
        assert {"state", "nonce", "code_challenge"} <= authorize.keys()
        assert authorize["redirect_uri"] == [lab.http_url("/session/oidc/callback")]
        assert set(authorize["scope"][0].split()) == {"openid", "email", "profile"}
        landed = ann.sign_in("s-ann")
        assert landed.status_code == 200, landed.text
        assert "Signed in as ann" in landed.text
        assert 'http-equiv="refresh" content="0; url=/tokens"' in landed.text
        assert ann.me().json()["name"] == "ann"
        page = ann.http.get(lab.http_url("/tokens"))
        assert "Your API tokens" in page.text and f"{issuer} (ann@example.edu)" in page.text

        again = Person(lab, issuer)
        again.set_claims("s-ann", email="ann@elsewhere.org", email_verified=True,
                         preferred_username="annie")  # fmt: skip
        assert again.sign_in("s-ann").status_code == 200
        assert again.me().json()["name"] == "ann"
        [identity] = lab.lab.service.accounts.identities("ann")
        assert (identity.issuer, identity.subject) == (issuer, "s-ann")


def test_a_second_person_with_the_same_name_gets_a_name_of_their_own(tmp_path, issuer):
    with lab_with(tmp_path, issuer) as lab:
        lab.lab.service.index.add_user("Ann")
        for subject in ("s-1", "s-2"):
            person = Person(lab, issuer)
            person.set_claims(subject, email="ann@example.edu", email_verified=True)
            assert person.sign_in(subject).status_code == 200
        names = {i.user for i in _all_identities(lab)}
        assert names == {"ann-2", "ann-3"}  # Ann is taken without case


def _all_identities(lab: Any) -> list[Any]:
    """Every identity the lab's index holds."""
    with lab.lab.service.index.engine.connect() as db:
        return list(db.execute(sa.select(identities)).all())


def test_a_forged_or_replayed_state_signs_nobody_in(tmp_path, issuer, caplog):
    """The callback with a state this browser was not given, or with one already
    used, is refused: no session, a page saying so, one line in the log."""
    with lab_with(tmp_path, issuer) as lab:
        ann = Person(lab, issuer)
        ann.set_claims("s-ann", email="ann@example.edu", email_verified=True)
        back = ann.authorize(ann.start(), "s-ann")
        query = parse_qs(urlsplit(back).query)
        forged = lab.http_url(f"/session/oidc/callback?code={query['code'][0]}&state=forged")
        refused = ann.http.get(forged)
        assert refused.status_code == 403
        assert "Nobody was signed in" in refused.text and "labd_session" not in refused.cookies
        assert ann.me().status_code == 401
        # the same browser, its genuine answer: the flow was spent by the forgery
        assert ann.http.get(back).status_code == 403
        # a fresh flow signs in; its answer, replayed, does not sign in again
        mallory = Person(lab, issuer)
        back = ann.authorize(ann.start(), "s-ann")
        assert ann.http.get(back).status_code == 200
        mallory.http.cookies.update(ann.http.cookies)
        mallory.http.cookies.delete("labd_session")
        assert mallory.http.get(back).status_code == 403
        assert mallory.me().status_code == 401
    refusals = [r for r in caplog.records if "OpenID sign-in refused" in r.getMessage()]
    assert len(refusals) == 3, [r.getMessage() for r in refusals]


def test_sign_up_limited_to_domains_and_invited_people(tmp_path, issuer):
    """With --oidc-allow-domain and --oidc-invite, only a verified address in the domain,
    or an invited one, makes an account; an unverified one does not."""
    with lab_with(tmp_path, issuer, domains=("example.edu",), invited=("bob@gmail.test",)) as lab:
        for subject, claims, ok in (
            ("s-1", {"email": "ann@example.edu", "email_verified": True}, True),
            ("s-2", {"email": "bob@gmail.test", "email_verified": True}, True),
            ("s-3", {"email": "eve@evil.test", "email_verified": True}, False),
            ("s-4", {"email": "mal@example.edu", "email_verified": False}, False),
        ):
            person = Person(lab, issuer)
            person.set_claims(subject, **claims)
            landed = person.sign_in(subject)
            assert (landed.status_code == 200) is ok, (subject, landed.text)
            assert (person.me().status_code == 200) is ok
        refused = landed.text
        assert "this lab makes accounts only for" in refused
        assert len(_all_identities(lab)) == 2


def test_a_signed_in_person_links_a_provider_to_their_password_account(tmp_path, issuer):
    """Signed in with a password, a person links their provider account from the tokens
    page; from then on the provider signs them in to that account."""
    with lab_with(tmp_path, issuer) as lab:
        accounts = lab.lab.service.accounts
        lab.lab.service.index.add_user("carol", token=False)
        accounts.set_password("carol", "a long password")
        carol = Person(lab, issuer)
        form = carol.http.get(lab.http_url("/session"))
        csrf = form.cookies.get("labd_csrf") or carol.http.cookies.get("labd_csrf")
        signed = carol.http.post(
            lab.http_url("/session"),
            data={"name": "carol", "password": "a long password", "csrf": csrf},
            headers={"origin": lab.http_url("").rstrip("/")},
        )
        assert signed.status_code == 303, signed.text
        tokens = carol.http.get(lab.http_url("/tokens"))
        assert "Sign in with Test University too" in tokens.text
        session_csrf = tokens.text.split('name="csrf" value="')[1].split('"')[0]
        start = carol.http.post(
            lab.http_url("/session/oidc/test/link"),
            data={"csrf": session_csrf},
            headers={"origin": lab.http_url("").rstrip("/")},
        )
        assert start.status_code in (302, 303), start.text
        carol.set_claims("s-carol", email="c@example.edu", email_verified=True)
        assert (
            carol.http.get(carol.authorize(start.headers["location"], "s-carol")).status_code == 200
        )
        other = Person(lab, issuer)
        assert other.sign_in("s-carol").status_code == 200
        assert other.me().json()["name"] == "carol"


# -- an untrustworthy provider -------------------------------------------------------------------


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def tampering(app: WSGI, change: Callable[[dict[str, Any]], None]) -> WSGI:
    """``app`` with its token endpoint's ID token changed by ``change`` (its claims) and
    signed again with the provider's own key: a provider that lies, or one that issues
    tokens for someone else."""
    from joserfc import jwk, jwt  # noqa: PLC0415 (the provider's own library, for this test only)
    from oidc_provider_mock._storage import storage  # noqa: PLC0415

    def wrapped(environ: dict[str, Any], start_response: Callable[..., Any]) -> Any:
        if environ.get("PATH_INFO") != "/oauth2/token":
            return app(environ, start_response)
        held: dict[str, Any] = {}

        def hold(status: str, headers: list[tuple[str, str]], *rest: Any) -> Any:
            held["status"], held["headers"] = status, headers
            return lambda data: None

        body = json.loads(b"".join(app(environ, hold)))
        with app.test_request_context():  # type: ignore[attr-defined]
            app.preprocess_request()  # type: ignore[attr-defined]  # the provider's globals
            key = jwk.RSAKey.import_key(storage.jwk.as_dict(is_private=True))
        head, payload, _ = body["id_token"].split(".")
        header = json.loads(base64.urlsafe_b64decode(head + "=="))
        claims = json.loads(base64.urlsafe_b64decode(payload + "=="))
        change(claims)
        body["id_token"] = jwt.encode(header, claims, key)
        data = json.dumps(body).encode()
        headers = [(k, v) for k, v in held["headers"] if k.lower() != "content-length"]
        start_response(held["status"], [*headers, ("Content-Length", str(len(data)))])
        return [data]

    return wrapped


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (lambda c: c.update(aud="someone-else"), "could not be trusted"),
        (lambda c: c.update(iss="http://127.0.0.1:1"), "could not be trusted"),
        (lambda c: c.update(exp=c["iat"] - 600), "could not be trusted"),
        (lambda c: c.update(nonce="not-the-one"), "could not be trusted"),
    ],
    ids=["wrong-audience", "wrong-issuer", "expired", "wrong-nonce"],
)
def test_an_id_token_that_is_not_for_this_lab_signs_nobody_in(tmp_path, change, said):
    app = oidc_provider_mock.app()
    with provider(tampering(app, change)) as issuer, lab_with(tmp_path, issuer) as lab:
        ann = Person(lab, issuer)
        ann.set_claims("s-ann", email="ann@example.edu", email_verified=True)
        refused = ann.sign_in("s-ann")
        assert refused.status_code == 403
        assert said in refused.text
        assert ann.me().status_code == 401
        assert _all_identities(lab) == []


def test_an_expired_id_token_from_the_provider_itself_signs_nobody_in(tmp_path):
    app = oidc_provider_mock.app(access_token_max_age=timedelta(seconds=-600))
    with provider(app) as issuer, lab_with(tmp_path, issuer) as lab:
        ann = Person(lab, issuer)
        ann.set_claims("s-ann", email="ann@example.edu", email_verified=True)
        assert ann.sign_in("s-ann").status_code == 403
        assert ann.me().status_code == 401


def test_a_person_who_says_no_at_the_provider_is_told_so(tmp_path, issuer):
    with lab_with(tmp_path, issuer) as lab:
        ann = Person(lab, issuer)
        url = ann.start()
        ann.http.get(url)
        denied = ann.http.post(url, data={"action": "deny"})
        assert denied.status_code == 302
        refused = ann.http.get(denied.headers["location"])
        assert refused.status_code == 403
        assert "you did not let the provider tell this lab who you are" in refused.text


def test_a_provider_that_is_away_is_a_page_saying_so(tmp_path):
    with provider(oidc_provider_mock.app()) as issuer:
        pass  # stopped: nothing answers there now
    with lab_with(tmp_path, issuer) as lab:
        reply = httpx.get(lab.http_url("/session/oidc"), timeout=30)
        assert reply.status_code == 503
        assert "cannot be reached now" in reply.text


def test_with_several_providers_each_has_its_address(tmp_path, issuer):
    """With two providers the sign-in page offers both, /session/oidc sends the person
    there to choose, /session/oidc/NAME goes to that one, and an unknown name is a page
    naming those there are."""
    config = OidcConfig(
        (
            Provider("uni", issuer, CLIENT, "shh", "Test University"),
            Provider("lab", issuer, "another-client", "", "The Lab's Own"),
        )
    )
    with running(lab_config(tmp_path / "data", robots=(), service={"oidc": config})) as lab:
        page = httpx.get(lab.http_url("/session"), timeout=30).text
        assert "Sign in with Test University" in page and "Sign in with The Lab&#39;s Own" in page
        choose = httpx.get(lab.http_url("/session/oidc?then=/robots"), timeout=30)
        assert (choose.status_code, choose.headers["location"]) == (303, "/session?then=/robots")
        to_lab = httpx.get(lab.http_url("/session/oidc/lab"), timeout=30)
        assert to_lab.status_code == 302
        assert "client_id=another-client" in to_lab.headers["location"]
        unknown = httpx.get(lab.http_url("/session/oidc/nope"), timeout=30)
        assert unknown.status_code == 404 and "through uni, lab, not" in unknown.text


def test_accounts_made_by_signing_in_count_with_the_address_s_sign_ups(tmp_path, issuer):
    """Five accounts an hour from one address, as with passwords: a sixth new person is
    refused, while a person who has an account still signs in."""
    with lab_with(tmp_path, issuer) as lab:
        for n in range(5):
            person = Person(lab, issuer)
            person.set_claims(f"s-{n}", email=f"p{n}@example.edu", email_verified=True)
            assert person.sign_in(f"s-{n}").status_code == 200
        sixth = Person(lab, issuer)
        sixth.set_claims("s-5", email="p5@example.edu", email_verified=True)
        refused = sixth.sign_in("s-5")
        assert refused.status_code == 403 and "too many sign-ups from your address" in refused.text
        again = Person(lab, issuer)
        assert again.sign_in("s-0").status_code == 200
