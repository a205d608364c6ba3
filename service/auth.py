"""API keys: random, shown once, stored as a SHA-256 digest.

A key carries 256 random bits, so a fast hash is enough (no password-style stretching: nothing
about it can be guessed); the digest is what a lookup compares, so the stored table cannot be
replayed as keys.
"""

from __future__ import annotations

import hashlib
import os
import secrets
from pathlib import Path

from sqlalchemy import select

from geomatch_core.errors import NotFound, Unauthenticated
from geomatch_core.models import ApiKey, Tenant, now
from geomatch_core.store import MetadataStore

KEY_PREFIX = "gm_"


def digest(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def create_key(store: MetadataStore, tenant_name: str) -> str:
    """A new key for ``tenant_name`` (the tenant is created on first use)."""
    tenant_name = tenant_name.strip()
    if not tenant_name or len(tenant_name) > 200:
        raise ValueError("tenant name must be 1 to 200 characters")
    key = KEY_PREFIX + secrets.token_urlsafe(32)
    with store.session() as s:
        tenant = s.scalar(select(Tenant).where(Tenant.name == tenant_name))
        if tenant is None:
            tenant = Tenant(name=tenant_name)
            s.add(tenant)
            s.flush()
        s.add(ApiKey(tenant_id=tenant.id, prefix=key[:10], digest=digest(key)))
    return key


MISSING_KEY = "missing API key: send 'Authorization: Bearer KEY'"


def authenticate(store: MetadataStore, key: str | None) -> str:
    """The tenant id of a valid, unrevoked key."""
    if not key:
        raise Unauthenticated(MISSING_KEY)
    with store.session() as s:
        row = s.scalar(select(ApiKey).where(ApiKey.digest == digest(key), ApiKey.revoked_at.is_(None)))
        if row is None:
            raise Unauthenticated("invalid or revoked API key")
        return row.tenant_id


def key_is_valid(store: MetadataStore, key: str) -> bool:
    try:
        authenticate(store, key)
    except Unauthenticated:
        return False
    return True


def list_keys(store: MetadataStore) -> list[dict[str, str | None]]:
    with store.session() as s:
        rows = s.execute(select(ApiKey, Tenant.name).join(Tenant).order_by(ApiKey.created_at)).all()
        return [
            {
                "tenant": name,
                "prefix": k.prefix,
                "created_at": k.created_at.isoformat(),
                "revoked_at": k.revoked_at.isoformat() if k.revoked_at else None,
            }
            for k, name in rows
        ]


def revoke(store: MetadataStore, prefix: str) -> int:
    with store.session() as s:
        rows = s.scalars(select(ApiKey).where(ApiKey.prefix == prefix, ApiKey.revoked_at.is_(None))).all()
        if not rows:
            raise NotFound(f"no active key starts with {prefix!r}")
        for r in rows:
            r.revoked_at = now()
        return len(rows)


KEY_FILE = "api-key.txt"


def embedded_key(store: MetadataStore, home: Path) -> str:
    """The embedded server's ready-to-use key: made once, kept in GEOMATCH_HOME/api-key.txt (0600),
    shown again at every start (only the digest is in the database)."""
    path = home / KEY_FILE
    if path.is_file():
        key = path.read_text().strip()
        if key_is_valid(store, key):
            return key
    key = create_key(store, "local")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key + "\n")
    return key
