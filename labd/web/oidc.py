"""Signing in through an OpenID Connect provider: the redirect flow, on the pages.

    GET  /session/oidc             with one provider, to it; with several, the sign-in page
    GET  /session/oidc/NAME        to provider NAME (``then``: where to go afterwards)
    POST /session/oidc/NAME/link   a signed-in person links NAME's account to theirs
    GET  /session/oidc/callback    where providers send people back

The flow is the authorization code flow with PKCE (S256), its ``state`` and ``nonce``
checked, done by Authlib's Starlette client: it keeps what it needs between the two legs
(state, nonce, code verifier) in a signed cookie of its own (``labd_oidc``, sent only to
``/session/oidc``, for ten minutes, SameSite=Lax, since the way back is a navigation
from the provider's site). The ID token's signature (the provider's published keys),
issuer, audience (the lab's client id), expiry and nonce are checked, and its issuer
must be the one the operator configured. The account is the one the (issuer, subject)
pair signs in to (``repository.accounts``), or a new one if the operator lets this
person sign up (``labd.oidc``). Then the browser session is the lab's own, as after a
password: ``GET /api/me`` answers for it, and tokens for the CLI are made on the tokens
page.

Anything wrong (a state that is not the one this browser was given, a replayed one, an
ID token for another client or from another issuer, an expired one, a provider that
cannot be reached, a person who may not sign up) signs nobody in, shows a page saying
so, and writes one line in the log.

The lab's session cookie is SameSite=Strict, so a browser does not send it on the
navigation that arrives from the provider's site, nor on a redirect that follows it:
the callback answers with a page that moves on to ``then`` by itself, a navigation of
the lab's own, on which the new cookie goes.
"""

from __future__ import annotations

import logging
from typing import Annotated, Any

from authlib.integrations.starlette_client import OAuth, OAuthError
from authlib.jose.errors import JoseError
from fastapi import APIRouter, FastAPI, Form, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from httpx import HTTPError
from starlette.middleware.sessions import SessionMiddleware

from labd.api.common import Caller, Lab
from labd.api.errors import ApiError, TooMany
from labd.api.throttle import Attempts
from labd.oidc import SCOPES, OidcConfig, Provider, wanted_name
from labd.web.forms import local
from labd.web.problems import PageRoute
from labd.web.render import page
from labd.web.session import CsrfChecked, Person, Viewer, set_session_cookie
from repository.errors import AccountError, ArchiveError
from repository.index import User

router = APIRouter(include_in_schema=False, route_class=PageRoute)
log = logging.getLogger("labd.web.oidc")
COOKIE = "labd_oidc"
STARTED = "labd_oidc_started"  # in that cookie: the provider, then, and whom to link
FLOW_AGE = 600  # seconds a person has to come back from the provider


def install(app: FastAPI, config: OidcConfig, secret: bytes, *, https: bool) -> None:
    """Add the sign-in flow to ``app`` for ``config``'s providers (none: nothing)."""
    if not config.providers:
        return
    oauth = OAuth()
    for provider in config.providers:
        kwargs: dict[str, Any] = {"scope": SCOPES, "code_challenge_method": "S256"}
        if not provider.client_secret:
            kwargs["token_endpoint_auth_method"] = "none"  # noqa: S105 (a public client: PKCE)
        oauth.register(
            provider.name,
            client_id=provider.client_id,
            client_secret=provider.client_secret or None,
            server_metadata_url=provider.metadata_url,
            client_kwargs=kwargs,
        )
    app.state.oidc = (config, oauth)
    app.include_router(router)
    app.add_middleware(
        SessionMiddleware,
        secret_key=secret.hex(),
        session_cookie=COOKIE,
        max_age=FLOW_AGE,
        path="/session/oidc",
        same_site="lax",
        https_only=https,
    )


def _configured(request: Request) -> tuple[OidcConfig, OAuth]:
    found: tuple[OidcConfig, OAuth] = request.app.state.oidc
    return found


def _provider(request: Request, name: str) -> Provider:
    config, _ = _configured(request)
    provider = config.provider(name)
    if provider is None:
        names = ", ".join(p.name for p in config.providers)
        raise ApiError(
            404,
            f"This lab signs people in through {names}, not {name!r}.",
            title="No such sign-in provider",
        )
    return provider


@router.get("/session/oidc")
async def start_default(request: Request, service: Lab, then: str = "/") -> Any:
    config, _ = _configured(request)
    if len(config.providers) > 1:  # the person chooses on the sign-in page
        return RedirectResponse(f"/session?then={local(then)}", status_code=303)
    return await _start(request, service, config.providers[0], then, link="")


@router.get("/session/oidc/callback", name="oidc_callback")
async def callback(request: Request, service: Lab, caller: Caller, viewer: Viewer) -> Any:
    started = request.session.pop(STARTED, None)
    if not isinstance(started, dict):
        return _refused(
            request,
            viewer,
            "this sign-in was not started in this browser, or it took over ten minutes",
            "no flow started",
        )
    config, oauth = _configured(request)
    provider = config.provider(str(started.get("provider")))
    if provider is None:  # the operator removed it meanwhile
        return _refused(request, viewer, "the provider is no longer one of this lab's", "gone")
    client = oauth.create_client(provider.name)
    try:
        token = await client.authorize_access_token(request)
    except OAuthError as err:
        return _refused(request, viewer, _said(err), f"{provider.name}: {err}")
    except JoseError as err:  # the ID token: its signature, issuer, audience, expiry, nonce
        said = f"the provider's answer could not be trusted ({err.error}: {err.description})"
        return _refused(request, viewer, said, f"{provider.name}: the ID token: {err}")
    except (HTTPError, ValueError) as err:
        return _refused(
            request, viewer, f"{provider.shown} could not be reached", f"{provider.name}: {err}"
        )
    claims = token.get("userinfo")
    if not claims:
        return _refused(request, viewer, "the provider sent no ID token", f"{provider.name}")
    issuer, subject = str(claims.get("iss", "")), str(claims.get("sub", ""))
    if issuer.rstrip("/") != provider.issuer.rstrip("/") or not subject:
        why = f"{provider.name}: the ID token's issuer is {issuer!r}, not {provider.issuer!r}"
        return _refused(request, viewer, "the ID token is not from the provider", why)
    email = str(claims.get("email") or "")
    try:
        user = _account(
            service,
            config,
            started,
            caller,
            issuer=issuer,
            subject=subject,
            claims=claims,
            email=email,
        )
    except TooMany as err:
        return _refused(request, viewer, str(err), f"{provider.name} subject {subject}: {err}")
    except (AccountError, ArchiveError) as err:
        return _refused(request, viewer, str(err), f"{provider.name} subject {subject}: {err}")
    log.info("%s signed in through %s (subject %s)", user.name, provider.name, subject)
    return _signed_in(request, service, user, started.get("then", "/"))


@router.get("/session/oidc/{name}")
async def start(request: Request, service: Lab, name: str, then: str = "/") -> Any:
    return await _start(request, service, _provider(request, name), then, link="")


@router.post("/session/oidc/{name}/link", dependencies=[CsrfChecked])
async def start_link(
    request: Request,
    service: Lab,
    name: str,
    person: Person,
    then: Annotated[str, Form()] = "/tokens",
) -> Any:
    """A signed-in person asks to sign in through ``name`` too: once the provider
    vouches for them, that account of theirs signs in to this one."""
    return await _start(request, service, _provider(request, name), then, link=person.name)


async def _start(
    request: Request, service: Lab, provider: Provider, then: str, *, link: str
) -> Any:
    _, oauth = _configured(request)
    client = oauth.create_client(provider.name)
    request.session[STARTED] = {"provider": provider.name, "then": local(then), "link": link}
    # where people reach the lab (behind a proxy, --public-url), else where this came to
    public = service.config.public_url
    callback = (
        f"{public}/session/oidc/callback" if public else str(request.url_for("oidc_callback"))
    )
    try:
        return await client.authorize_redirect(request, callback)
    except (HTTPError, OAuthError, ValueError) as err:
        log.warning("OpenID sign-in through %s cannot start: %s", provider.name, err)
        raise ApiError(
            503,
            f"{provider.shown} cannot be reached now ({err}); try again later, or sign in"
            " with your password.",
            title="The sign-in provider is away",
        ) from None


def _account(
    service: Lab,
    config: OidcConfig,
    started: dict[str, Any],
    caller: Attempts,
    *,
    issuer: str,
    subject: str,
    claims: Any,
    email: str,
) -> User:
    """The account this person signs in to: theirs, the one they link, or a new one."""
    linking = str(started.get("link") or "")
    if linking:
        service.accounts.link_identity(linking, issuer, subject, email)
        return service.index.user(linking)
    user = service.accounts.identity(issuer, subject)
    if user is not None:
        return user
    refused = config.refusal(claims)
    if refused:
        raise AccountError(refused)
    caller.check("signup", "sign-ups from your address")  # as many as with passwords
    user = service.accounts.sign_up_identity(issuer, subject, wanted_name(claims), email)
    caller.fail("signup")  # every account made counts
    return user


def _signed_in(request: Request, service: Lab, user: User, then: str) -> HTMLResponse:
    cookie, _ = service.accounts.open_session(user)
    response = page(request, "signed_in.html", {"then": local(then), "name": user.name}, user=user)
    set_session_cookie(response, request, cookie, service.accounts.session_age)
    response.headers["Cache-Control"] = "no-store"
    return response


def _said(err: OAuthError) -> str:
    """What the person reads of a refused flow: the provider's own refusal, or that the
    answer could not be trusted."""
    if err.error == "access_denied":
        return "you did not let the provider tell this lab who you are"
    if err.error == "mismatching_state" or "state" in str(err.description or ""):
        return "this sign-in's state is not the one this browser was given (a forged or old link)"
    return f"the provider's answer could not be trusted ({err.error or err.description})"


def _refused(request: Request, viewer: User | None, said: str, logged: str) -> HTMLResponse:
    log.warning("OpenID sign-in refused, nobody signed in: %s", logged)
    return page(
        request,
        "signin_refused.html",
        {"problem": said},
        user=viewer,
        status_code=403,
    )
