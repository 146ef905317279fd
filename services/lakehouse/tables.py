"""The lakehouse's Iceberg catalog and tables: pyiceberg's SQL catalog (named `fleet`) on the depot's
own catalog database, in the layout of Iceberg's JDBC catalog, so Trino and Spark can point at it;
data and metadata under the warm store's `lakehouse/` prefix.

The embedded default (a DuckDB catalog file) keeps the Iceberg catalog in a SQLite file beside it:
pyiceberg's SQL catalog does not run on DuckDB. The store's credentials go to pyiceberg's file IO in
memory only: neither the catalog's rows nor the tables' metadata hold them.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

from sqlalchemy.exc import DBAPIError, IntegrityError

from services.storage.objectstore import ObjectStore

# pyiceberg is imported where the catalog is first opened: its third of a second is not paid by a
# depot start, nor by a depot that never reads or writes the tables
if TYPE_CHECKING:
    from pyiceberg.catalog.sql import SqlCatalog
    from pyiceberg.table import Table

CATALOG_NAME = "fleet"
PREFIX = "lakehouse"  # under the warm store's root
SQLITE_FILE = "lakehouse.db"  # beside an embedded DuckDB catalog
# Merge small manifests as commits come (one or a few runs each), so a scan's planning reads a few
# manifests, not one per commit.
TABLE_PROPERTIES = {"commit.manifest-merge.enabled": "true", "write.parquet.compression-codec": "zstd"}


@dataclass
class Lakehouse:
    """The Iceberg catalog and where its tables live. The catalog is opened on first use (opening it
    connects to the database: a depot starts, and says so in /readyz, while its database is down),
    the tables are made on first use."""

    properties: dict[str, Any] = field(repr=False)  # pyiceberg's catalog and file IO settings
    warehouse: str
    _catalog: SqlCatalog | None = field(default=None, init=False, repr=False)
    _made: set[str] = field(default_factory=set, init=False, repr=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    @property
    def catalog(self) -> SqlCatalog:
        from pyiceberg.catalog.sql import SqlCatalog

        with self._lock:
            for attempt in range(3):
                if self._catalog is not None:
                    break
                try:  # makes pyiceberg's two tables if they are missing
                    self._catalog = SqlCatalog(CATALOG_NAME, **self.properties)
                except DBAPIError:
                    if attempt == 2:  # another node made them at the same moment: found on the next try
                        raise
            assert self._catalog is not None
            return self._catalog

    def table(self, name: str) -> Table:
        """The table as its latest commit left it (made with its schema and partitions if new)."""
        from pyiceberg.exceptions import NamespaceAlreadyExistsError, NoSuchTableError, TableAlreadyExistsError

        from services.lakehouse.schemas import NAMESPACE, partition_spec, schema

        if name in self._made:
            try:
                return self.catalog.load_table((NAMESPACE, name))
            except NoSuchTableError:
                self._made.discard(name)  # dropped by hand: made again below
        catalog = self.catalog
        with self._lock:
            for attempt in range(3):
                try:
                    catalog.create_namespace_if_not_exists(NAMESPACE)
                    table = catalog.create_table_if_not_exists(
                        (NAMESPACE, name),
                        schema(name),
                        location=f"{self.warehouse}/{NAMESPACE}/{name}",
                        partition_spec=partition_spec(name),
                        properties=TABLE_PROPERTIES,
                    )
                    break
                except (IntegrityError, NamespaceAlreadyExistsError, TableAlreadyExistsError):
                    if attempt == 2:  # another node made it at the same moment: found on the next try
                        raise
            self._made.add(name)
            return table

    def close(self) -> None:
        with self._lock:
            if self._catalog is not None:
                self._catalog.engine.dispose()


def open_lakehouse(catalog_url: str, warm: ObjectStore) -> Lakehouse:
    """The lakehouse of the depot whose catalog is at `catalog_url` and warm tier is `warm`."""
    # pyiceberg warns of each commit it makes again after another writer's: routine with many nodes,
    # and the sync says so itself (services.lakehouse.sync)
    logging.getLogger("pyiceberg.table").setLevel(logging.ERROR)
    warehouse = f"{warm.url.rstrip('/')}/{PREFIX}"
    properties = {"uri": sql_catalog_uri(catalog_url), "warehouse": warehouse, **file_io_properties(warm)}
    return Lakehouse(properties, warehouse)


def sql_catalog_uri(catalog_url: str) -> str:
    """Where pyiceberg's SQL catalog keeps its two tables: the depot's Postgres itself, or a SQLite
    file beside an embedded DuckDB catalog."""
    parsed = urlparse(catalog_url)
    if parsed.scheme == "duckdb":
        beside = Path(parsed.path).parent if parsed.path not in ("", "/:memory:") else None
        if beside is None:
            raise ValueError("the lakehouse needs a catalog on disk: an in-memory DuckDB catalog has no folder")
        return f"sqlite:///{beside / SQLITE_FILE}"
    if parsed.scheme in ("postgresql", "postgres"):
        return "postgresql+psycopg" + catalog_url[len(parsed.scheme) :]
    return catalog_url


def file_io_properties(warm: ObjectStore) -> dict[str, Any]:
    """pyiceberg's file IO settings for the warm store: its S3 endpoint and credentials, if any."""
    access = getattr(warm, "access", None)
    if access is None:
        return {}
    found = access()
    props: dict[str, Any] = {"py-io-impl": "pyiceberg.io.pyarrow.PyArrowFileIO", "s3.region": found["region"]}
    if found["endpoint"]:
        scheme = "https" if found["use_ssl"] else "http"
        props |= {"s3.endpoint": f"{scheme}://{found['endpoint']}", "s3.force-virtual-addressing": False}
    if found["key_id"]:
        props |= {"s3.access-key-id": found["key_id"], "s3.secret-access-key": found["secret"]}
    if found["session_token"]:
        props["s3.session-token"] = found["session_token"]
    return props
