"""FastAPI dependencies, as ``Annotated`` aliases the routes take as parameters."""

from __future__ import annotations

from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from app.core.context import Gateway
from app.core.problems import ProblemError
from app.core.security import find_key
from workers.models import ApiKey
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


def _authenticate(gateway: Gateway, credentials: HTTPAuthorizationCredentials | None) -> ApiKey:
    if credentials is None:
        raise ProblemError(401, "This request needs an API key: send 'Authorization: Bearer "
                           "<key>' (create one with `volumesh keys create --name NAME`).",
                           kind="unauthorized", headers=_CHALLENGE)
    with gateway.sessions() as session:
        row = find_key(session, credentials.credentials)
    if row is None:
        raise ProblemError(401, "The API key is unknown or revoked.", kind="unauthorized",
                           headers=_CHALLENGE)
    return row


async def require_api_key(gateway: GatewayDep, credentials: BearerDep) -> ApiKey:
    """Every write needs a live API key (one indexed lookup, done on the loop)."""
    return _authenticate(gateway, credentials)


async def read_access(gateway: GatewayDep, credentials: BearerDep) -> ApiKey | None:
    """Reads need a key only when VOLUMESH_REQUIRE_AUTH_FOR_READS is set."""
    if not gateway.settings.require_auth_for_reads:
        return None
    return _authenticate(gateway, credentials)


ApiKeyDep = Annotated[ApiKey, Depends(require_api_key)]
ReadAccessDep = Annotated[ApiKey | None, Depends(read_access)]
