"""FastAPI dependencies, as ``Annotated`` aliases the routes take as parameters."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from app.core.context import Gateway
from app.core.problems import ProblemError
from app.core.security import Caller, find_caller
from workers.settings import Settings
from workers.storage import Storage

_bearer = HTTPBearer(auto_error=False, description="An API key from `volumesh keys create`.")


# Dependencies are ``async def`` so FastAPI calls them on the event loop: a plain ``def`` would
# cost a thread hop each, which dominates a cheap request such as GET /jobs/{id}.


async def get_gateway(request: Request) -> Gateway:
    gateway: Gateway = request.app.state.gateway
    return gateway


GatewayDep = Annotated[Gateway, Depends(get_gateway)]


async def get_settings(gateway: GatewayDep) -> Settings:
    return gateway.settings


async def get_storage(gateway: GatewayDep) -> Storage:
    return gateway.storage


async def get_session(gateway: GatewayDep) -> AsyncIterator[Session]:
    """A job-store session (opening one does no I/O; queries run where the route runs)."""
    with gateway.sessions() as session:
        yield session


SettingsDep = Annotated[Settings, Depends(get_settings)]
StorageDep = Annotated[Storage, Depends(get_storage)]
SessionDep = Annotated[Session, Depends(get_session)]
BearerDep = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]

_CHALLENGE = {"WWW-Authenticate": 'Bearer realm="volumesh"'}


def authenticate(gateway: Gateway, credentials: HTTPAuthorizationCredentials | None) -> Caller:
    """The caller of a request, or a 401 problem (one indexed read, done on the loop)."""
    if credentials is None:
        raise ProblemError(401, "This request needs an API key: send 'Authorization: Bearer "
                           "<key>' (create one with `volumesh keys create --name NAME`).",
                           kind="unauthorized", headers=_CHALLENGE)
    caller = find_caller(gateway.engine, credentials.credentials)
    if caller is None:
        raise ProblemError(401, "The API key is unknown or revoked.", kind="unauthorized",
                           headers=_CHALLENGE)
    return caller


async def require_caller(gateway: GatewayDep, credentials: BearerDep) -> Caller:
    """Every request to a resource needs a live API key; it sees only what its owner owns."""
    return authenticate(gateway, credentials)


CallerDep = Annotated[Caller, Depends(require_caller)]
