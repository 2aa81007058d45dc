"""Keeping credentials out of everything ftrain prints or persists (logs, manifests, configs, exported policies).

Torch-free and fsspec-free: the config module and the supervisor use it too.
"""

from __future__ import annotations

from urllib.parse import urlsplit, urlunsplit

SECRET_OPTIONS = frozenset(
    {"key", "secret", "token", "password", "aws_access_key_id", "aws_secret_access_key", "aws_session_token"}
)
"""fsspec/s3fs storage options that hold credentials."""

HIDDEN = "***"


def display_url(url: str) -> str:
    """``url`` without the credentials a URL may carry (``s3://key:secret@bucket/...`` -> ``s3://bucket/...``)."""
    parts = urlsplit(url) if "://" in url else None
    if parts is None or "@" not in parts.netloc:
        return url
    return urlunsplit(parts._replace(netloc=parts.netloc.rpartition("@")[2]))


def redact_options(options: dict) -> dict:
    """A copy of fsspec ``options`` with credential values hidden and URLs stripped of user information."""
    redacted = {}
    for name, value in options.items():
        if isinstance(value, dict):
            redacted[name] = redact_options(value)
        elif name in SECRET_OPTIONS and value:
            redacted[name] = HIDDEN
        elif isinstance(value, str):
            redacted[name] = display_url(value)
        else:
            redacted[name] = value
    return redacted
