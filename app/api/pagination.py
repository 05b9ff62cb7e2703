"""One page of a list endpoint: the ``limit``/``offset`` parameters and the query behind them."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query
from sqlalchemy import Select, func, select
from sqlalchemy.orm import Session

PageLimit = Annotated[int, Query(ge=1, le=100, description="Items per page.")]
PageOffset = Annotated[int, Query(ge=0, le=1_000_000, description="Items to skip.")]


def fetch_page(session: Session, query: Select[Any], order_by: tuple[Any, ...], limit: int,
               offset: int) -> tuple[list[Any], int]:
    """(the rows of the page, the total number of rows the query matches)."""
    total = session.scalar(select(func.count()).select_from(query.subquery())) or 0
    rows = list(session.scalars(query.order_by(*order_by).limit(limit).offset(offset)))
    return rows, total
