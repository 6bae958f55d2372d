"""A user's own account through the API: who am I, and my tokens.

    GET  /api/me                       the user the token or sign-in names
    GET  /api/tokens                   my tokens: labels and dates, never the tokens
    POST /api/tokens                   a new token (shown once): {"label": "..."}
    POST /api/tokens/{id}/revoke       revoke one of my tokens; it stops working at once

The operator lists, revokes and rotates anyone's with ``labd users``.
"""

from __future__ import annotations

import datetime as dt

from fastapi import APIRouter
from pydantic import BaseModel, Field

from labd.api.common import Lab, Writer
from labd.api.errors import responses
from labd.api.models import Id
from repository.accounts import Token
from repository.units import moment

router = APIRouter(tags=["accounts"])


class Me(BaseModel):
    """The user a request writes as."""

    name: str
    worker: bool = Field(description="a worker's token: it may claim and file trials")
    password: bool = Field(description="whether they can sign in on the pages")


class TokenView(BaseModel):
    """One API token as its owner sees it listed."""

    id: int
    label: str
    created: dt.datetime
    revoked: dt.datetime | None = Field(description="when it was revoked; null: it works")


class TokenList(BaseModel):
    tokens: list[TokenView]


class NewTokenRequest(BaseModel):
    label: str = Field(max_length=128, description="what it is for: 'my laptop', 'CI'")


class NewToken(BaseModel):
    """A new token: this is the only time the lab shows it."""

    token: str
    listed: TokenView


def token_view(token: Token) -> TokenView:
    return TokenView(
        id=token.id,
        label=token.label,
        created=moment(token.created),
        revoked=None if token.revoked is None else moment(token.revoked),
    )


@router.get("/api/me", responses=responses(401, 403))
def me(service: Lab, user: Writer) -> Me:
    """Who the token or the sign-in is."""
    return Me(name=user.name, worker=user.worker, password=service.accounts.has_password(user.name))


@router.get("/api/tokens", responses=responses(401, 403))
def tokens(service: Lab, user: Writer) -> TokenList:
    """My tokens, newest first (revoked ones too, with when)."""
    return TokenList(tokens=[token_view(t) for t in service.accounts.tokens(user.name)])


@router.post("/api/tokens", status_code=201, responses=responses(401, 403))
def new_token(body: NewTokenRequest, service: Lab, user: Writer) -> NewToken:
    """A new token for me; the answer is the only place it is ever shown."""
    listed, token = service.accounts.new_token(user.name, body.label)
    return NewToken(token=token, listed=token_view(listed))


@router.post("/api/tokens/{token_id}/revoke", responses=responses(401, 403, 404))
def revoke_token(token_id: Id, service: Lab, user: Writer) -> TokenView:
    """Revoke one of my tokens: it stops working at once."""
    return token_view(service.accounts.revoke_token(user.name, token_id))
