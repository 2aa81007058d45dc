"""Keeping credentials out of everything ftrain prints or persists (logs, manifests, configs, exported policies,
the supervisor's record of the commands it ran).

Torch-free and fsspec-free: the config module and the supervisor use it too.
"""

from __future__ import annotations

from urllib.parse import urlsplit, urlunsplit

import yaml

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
    return {
        name: HIDDEN if name in SECRET_OPTIONS and value and not isinstance(value, dict) else _redact(value)
        for name, value in options.items()
    }


def _redact(value: object) -> object:
    if isinstance(value, dict):
        return redact_options(value)
    if isinstance(value, list):
        return [_redact(item) for item in value]
    if isinstance(value, str):
        return display_url(value)
    return value


def redact_command(words: list[str]) -> list[str]:
    """A command line fit to log: URLs without user information, and in every ``key=value`` word (a config
    override, ``--option=value``) the value of a credential option hidden, at any depth of a YAML mapping value
    (``storage.options={key: ..., secret: ...}``, ``storage.options.secret=...``)."""
    return [_redact_word(word) for word in words]


def _redact_word(word: str) -> str:
    key, sep, raw = word.partition("=")
    if not sep or "://" in key:
        return display_url(word)
    name = key.rpartition(".")[2]
    if name in SECRET_OPTIONS:
        return f"{key}={HIDDEN}"
    try:
        value = yaml.safe_load(raw)  # as the config reads an override
    except yaml.YAMLError:
        value = raw
    redacted = _redact(value)
    if redacted == value:
        return word
    if isinstance(redacted, str):
        return f"{key}={redacted}"
    return f"{key}={yaml.safe_dump(redacted, default_flow_style=True, sort_keys=False, width=1 << 30).strip()}"
