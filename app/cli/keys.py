"""`volumesh keys create|list|revoke`: API keys of the gateway (stored hashed)."""

from __future__ import annotations

from typing import Annotated

import typer

from app.cli import app

keys_app = typer.Typer(help="Create, list and revoke API keys.", no_args_is_help=True)
app.add_typer(keys_app, name="keys")


def _sessions():  # type: ignore[no-untyped-def]
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.settings import get_settings

    engine = make_engine(get_settings())
    init_db(engine)
    return make_sessionmaker(engine)


@keys_app.command("create")
def create(
    name: Annotated[str, typer.Option("--name", help="Who or what the key is for.")],
    project: Annotated[str | None, typer.Option(
        "--project", help="Keys of one project see and use each other's captures, jobs, "
        "assets and rigs; without one, a key sees only its own.")] = None,
    admin: Annotated[bool, typer.Option(
        "--admin", help="Sees and acts on everything, and reads /metrics.")] = False,
) -> None:
    """Creates a key and prints it alone on the last line (it is not shown again)."""
    from app.core.security import create_key

    with _sessions()() as session:
        row, key = create_key(session, name, project=project, admin=admin)
    scope = "admin" if admin else f"project {project!r}" if project else "its own work"
    typer.echo(f"created API key {row.id} named {row.name!r} ({scope}); store it now, it is "
               "not shown again:", err=True)
    typer.echo(key)


@keys_app.command("list")
def list_() -> None:
    """Lists keys: id, name, prefix, scope (admin, project or own), created, revoked."""
    from app.core.security import list_keys

    with _sessions()() as session:
        rows = list_keys(session)
    for row in rows:
        revoked = f"revoked {row.revoked_at:%Y-%m-%d %H:%M}" if row.revoked_at else "live"
        scope = "admin" if row.admin else f"project:{row.project}" if row.project else "own"
        typer.echo(f"{row.id}  {row.name:<24}  {row.prefix}…  {scope:<20}  "
                   f"{row.created_at:%Y-%m-%d %H:%M}  {revoked}")


@keys_app.command("revoke")
def revoke(key: Annotated[str, typer.Argument(help="Key id, or name (revokes all of that "
                                              "name).")]) -> None:
    """Revokes keys at once: requests with them get 401 from then on."""
    from app.core.security import revoke_key

    with _sessions()() as session:
        revoked = revoke_key(session, key)
    if not revoked:
        raise ValueError(f"KEY: no live key has the id or name {key!r}")
    for row in revoked:
        typer.echo(f"revoked {row.id} ({row.name})")
