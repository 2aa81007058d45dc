"""Keeping credentials out of everything ftrain prints or persists (logs, manifests, configs, exported policies,
the supervisor's record of the commands it ran).

Torch-free and fsspec-free: the config module and the supervisor use it too.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from urllib.parse import SplitResult, unquote, urlsplit, urlunsplit

import yaml

SECRET_OPTIONS = frozenset(
    {"key", "secret", "token", "password", "aws_access_key_id", "aws_secret_access_key", "aws_session_token"}
    | {"account_key", "connection_string", "sas_token", "credential", "client_secret"}
    | {"private_key", "private_key_id", "refresh_token"}
)
"""fsspec storage options that hold credentials: s3fs's, adlfs's (Azure), and those of a gcsfs ``token`` given as a
service account's or a user's credentials (a dict: its values are redacted key by key)."""
SECRET_QUERY = frozenset(
    {"sig", "signature", "x-amz-signature", "x-amz-credential", "x-amz-security-token", "x-goog-signature"}
    | {"x-goog-credential", "token", "access_token", "sas_token", "password", "secret", "key", "code"}
)
"""Query parameters of a URL whose values are credentials (compared in lower case): an Azure SAS token's signature
(``sig=``), an S3 or GCS presigned URL's (``X-Amz-Signature=``...), and the like."""
CONTAINER_AT_ACCOUNT = frozenset({"abfs", "abfss", "az", "wasb", "wasbs"})
"""Azure's URL schemes, where ``container@account...`` names a container, not a user: no credential."""

HIDDEN = "***"
ARGUMENTS_ENV = "FTRAIN_TRAIN_ARGUMENTS"
"""Where the supervisor passes ``ftrain train`` arguments that carry credentials (see ``hide_credentials``)."""


class Url(str):
    """A URL that may carry credentials (``s3://key:secret@bucket/prefix``), as the config holds it: its text form
    (``str``, ``repr``, f-strings, ``%s``, logging) is the URL without them, so that no message or record can print a
    secret by formatting it. ``reveal()`` is the form with credentials, for the one place that needs it: opening the
    storage (fsspec, MLflow). It stays a ``str`` for everything that compares or parses it; a string built from it by
    ``+`` or slicing is a plain ``str``, so code that builds text from it formats it instead."""

    def __new__(cls, url: str = "") -> Url:
        return super().__new__(cls, str.__str__(url))  # str(url) of a Url would drop its credentials

    def __str__(self) -> str:
        return display_url(self)

    def __repr__(self) -> str:
        return repr(display_url(self))

    def __format__(self, spec: str) -> str:
        return format(display_url(self), spec)

    def reveal(self) -> str:
        """The URL with its credentials, as given."""
        return str.__str__(self)


def display_url(url: str) -> str:
    """``url`` without the credentials a URL may carry, as a plain ``str``: its user information
    (``s3://key:secret@bucket/...`` -> ``s3://bucket/...``) and the values of its credential query parameters
    (``?sv=...&sig=...`` -> ``?sv=...&sig=***``)."""
    url = str.__str__(url)
    parts, user, fields = _split(url)
    if not user and not any(_secret_query(name) for name, _, _ in fields):
        return url
    netloc = parts.netloc.rpartition("@")[2] if user else parts.netloc
    query = "&".join(f"{name}{eq}{HIDDEN if _secret_query(name) else value}" for name, eq, value in fields)
    return urlunsplit(parts._replace(netloc=netloc, query=query))


def _split(url: str) -> tuple[SplitResult | None, str, list[tuple[str, str, str]]]:
    """``url`` split (None: not a URL), its user information if that is a credential (an Azure ``container@account``
    is none), and its query's fields as ``(name, "=", value)``."""
    if "://" not in url:
        return None, "", []
    parts = urlsplit(url)
    user, at, _ = parts.netloc.rpartition("@")
    credential = user if at and not (parts.scheme in CONTAINER_AT_ACCOUNT and ":" not in user) else ""
    return parts, credential, [field.partition("=") for field in parts.query.split("&")] if parts.query else []


def display_urls(data: object) -> object:
    """``data`` (dicts and lists, as ``dataclasses.asdict`` makes them) with every ``Url`` in it as its text form: a
    plain ``str``, which ``json`` and ``yaml`` write as it reads (a ``str`` subclass they would write raw)."""
    if isinstance(data, dict):
        return {key: display_urls(value) for key, value in data.items()}
    if isinstance(data, list | tuple):
        return type(data)(display_urls(item) for item in data)
    return display_url(data) if isinstance(data, Url) else data


def redact_options(options: dict) -> dict:
    """A copy of fsspec ``options`` with credential values hidden and URLs stripped of user information."""
    return {
        name: HIDDEN if name in SECRET_OPTIONS and value and not isinstance(value, dict) else _redact(value)
        for name, value in options.items()
    }


def without_hidden(options: dict) -> dict:
    """A copy of fsspec ``options`` without the values ``redact_options`` hid, at any depth: a config saved with them
    (``<log_dir>/config.yaml``, a manifest's) read back takes its credentials from where they came, the environment or
    ``--storage-option``, instead of sending ``***`` as one."""
    return {
        name: _without_hidden(value)
        for name, value in options.items()
        if not (name in SECRET_OPTIONS and value == HIDDEN)
    }


def _without_hidden(value: object) -> object:
    if isinstance(value, dict):
        return without_hidden(value)
    if isinstance(value, list):
        return [_without_hidden(item) for item in value]
    return value


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


def hide_credentials(words: list[str]) -> tuple[list[str], dict[str, str]]:
    """``words`` (``ftrain train`` arguments) fit for a command line, which every user of the machine can read
    (``ps``, ``/proc/<pid>/cmdline``): redacted as ``redact_command`` does, and the environment that gives the
    process the real words (``/proc/<pid>/environ`` is readable by its user only): empty if nothing was hidden."""
    shown = redact_command(words)
    return shown, ({ARGUMENTS_ENV: json.dumps(words)} if shown != words else {})


def reveal_credentials(words: list[str], environ: Mapping[str, str]) -> list[str]:
    """The real arguments behind ``words`` as ``hide_credentials`` hid them: the ones in ``environ`` if these are
    what ``words`` shows, else ``words`` (a variable left over from another command line is ignored)."""
    real = json.loads(environ.get(ARGUMENTS_ENV) or "null")
    return real if isinstance(real, list) and redact_command(real) == words else words


SHORT_SECRET = 8
"""A secret shorter than this many characters is blanked only where it stands alone, not inside a longer word:
blanking a one-letter password wherever its letter occurs would garble the whole message."""


def scrub(exc: BaseException, secrets: list[str]) -> str:
    """One line naming the exception, with every secret blanked out (a short one where it stands alone)."""
    text = " ".join(f"{type(exc).__name__}: {exc}".split())
    for secret in sorted({s for s in secrets if s}, key=len, reverse=True):
        if len(secret) >= SHORT_SECRET:
            text = text.replace(secret, HIDDEN)
        else:
            text = re.sub(rf"(?<![A-Za-z0-9]){re.escape(secret)}(?![A-Za-z0-9])", HIDDEN, text)
    return text


def secret_values(options: dict) -> list[str]:
    """Credential options, and the ``user:password`` part of any URL among the options (e.g. an endpoint)."""
    values = []
    for name, value in options.items():
        if isinstance(value, dict):
            values += secret_values(value)
        elif isinstance(value, str) and name in SECRET_OPTIONS:
            values.append(value)
        elif isinstance(value, str) and "://" in value:
            values += url_secrets(value)
    return values


def _secret_query(name: str) -> bool:
    return unquote(name).lower() in SECRET_QUERY


def url_secrets(url: str) -> list[str]:
    """The credentials of ``url``: what ``display_url`` takes out (an Azure ``container@account`` names none), as
    given and unquoted."""
    _, user, fields = _split(str.__str__(url))
    values = [value for name, _, value in fields if value and _secret_query(name)]
    found = [*([user, *user.split(":")] if user else []), *values]
    return [text for secret in found for text in {secret, unquote(secret)}]
