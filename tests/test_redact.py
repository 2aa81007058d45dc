"""The one redaction module: URLs, storage options and command lines without credentials."""

import json
import logging
import pickle

import yaml

from ftrain.config import load_config
from ftrain.redact import (
    HIDDEN,
    Url,
    display_url,
    hide_credentials,
    redact_command,
    redact_options,
    reveal_credentials,
    scrub,
    secret_values,
    url_secrets,
)


def test_urls_and_options_lose_their_credentials() -> None:
    assert display_url("s3://KEY:SECRET@bucket/run") == "s3://bucket/run"
    assert display_url("runs/hc") == "runs/hc"
    assert display_url("abfs://box@account.dfs.core.windows.net/run") == "abfs://box@account.dfs.core.windows.net/run"
    assert display_url("abfs://box:KEY@account/run") == "abfs://account/run"
    assert redact_options({"account_name": "acct", "account_key": "KEY", "connection_string": "AccountKey=KEY"}) == {
        "account_name": "acct",
        "account_key": HIDDEN,
        "connection_string": HIDDEN,
    }
    options = {"endpoint_url": "http://u:p@127.0.0.1:9000", "key": "KEY", "secret": "SECRET", "config_kwargs": {}}
    assert redact_options(options) == {
        "endpoint_url": "http://127.0.0.1:9000",
        "key": HIDDEN,
        "secret": HIDDEN,
        "config_kwargs": {},
    }


def test_credentials_in_a_urls_query_are_hidden_and_known_for_scrubbing() -> None:
    """An Azure SAS token or an S3 presigned URL pasted as the storage: the signature's values go, the rest stays."""
    sas = "abfs://box@account.dfs.core.windows.net/run?sv=2022-11-02&se=2026-12-01&sig=AbC%2Bdef%3D"
    assert display_url(sas) == "abfs://box@account.dfs.core.windows.net/run?sv=2022-11-02&se=2026-12-01&sig=***"
    presigned = "s3://b/run?X-Amz-Algorithm=AWS4-HMAC-SHA256&X-Amz-Expires=3600&X-Amz-Signature=ff00&versionId=3"
    assert display_url(presigned) == presigned.replace("ff00", "***")  # the signature, not its algorithm or expiry
    assert url_secrets(presigned) == ["ff00"]
    assert set(url_secrets(sas)) == {"AbC%2Bdef%3D", "AbC+def="}
    assert set(url_secrets("s3://KEY:SECRET@b/run?token=T")) == {"KEY:SECRET", "KEY", "SECRET", "T"}
    assert url_secrets("s3://b/run?versionId=3") == [] and url_secrets("abfs://box@account/run") == []
    assert "AbC" not in scrub(OSError(f"request to {Url(sas).reveal()} failed"), url_secrets(sas))


def test_a_short_secret_is_blanked_where_it_stands_alone_and_the_message_stays_readable() -> None:
    """A one-letter user and password (``s3://a:b@...``): blanked in the URL, not in every word with an a or a b."""
    url = "http://a:b@127.0.0.1:9000/bucket"
    message = scrub(OSError(f"cannot reach {url}: connection refused by the server"), url_secrets(url))
    assert message == "OSError: cannot reach http://***@127.0.0.1:9000/bucket: connection refused by the server"
    long = "s3://AKIAEXAMPLE:wJalrXUtnFEMI@b/run"  # a long one goes wherever it is, inside a word too
    assert "AKIAEXAMPLE" not in scrub(OSError(f"no key xAKIAEXAMPLEx for {long}"), url_secrets(long))


def test_a_config_url_formats_without_its_credentials_and_reveals_them_only_when_asked(caplog) -> None:
    config = load_config(
        None,
        [
            "algorithm.class_name=Distillation",
            "teacher=s3://AK:SK@bucket/teacher",
            "resume=s3://AK:SK@bucket/old",
            "log.mlflow.tracking_uri=http://u:PW@h",
        ],
        storage="s3://AK:SK@bucket/run",
    )
    urls = [config.storage.url, config.teacher, config.log.mlflow.tracking_uri]
    assert all(isinstance(url, Url) for url in urls)
    with caplog.at_level(logging.INFO):
        logging.getLogger("test").info("storage %s, teacher %r", config.storage.url, config.teacher)
    shown = [repr(config), caplog.text]
    shown += [text for url in urls for text in (f"{url}", f"{url!r}", f"{url:>40}", str(url), repr(url))]
    assert not any("SK" in text or "PW" in text for text in shown), shown
    assert f"{config.storage.url}" == "s3://bucket/run" and type(str(config.storage.url)) is str
    assert config.storage.url.reveal() == "s3://AK:SK@bucket/run" == config.storage.url  # compares as given
    assert Url(config.storage.url).reveal() == "s3://AK:SK@bucket/run"
    assert pickle.loads(pickle.dumps(config.teacher)).reveal() == "s3://AK:SK@bucket/teacher"  # to a sender process
    public = config.public_dict()  # plain strs: json writes a Url raw, yaml's safe dumper refuses one
    assert "SK" not in json.dumps(public) + yaml.safe_dump(public) and "PW" not in json.dumps(public)


def test_command_lines_lose_their_credentials_and_keep_the_rest() -> None:
    command = [
        "torchrun",
        "--nproc-per-node=2",
        "configs/smoke.yaml",
        "--storage",
        "s3://KEY:SECRET@bucket/run",
        "--storage=s3://KEY:SECRET@bucket/run",
        "storage.options={endpoint_url: 'http://127.0.0.1:9000', key: KEY, secret: SECRET}",
        "storage.options.secret=SECRET",
        "teacher='s3://KEY:SECRET@bucket/teacher'",
        "hooks=[{target: 'probe:Hook', kwargs: {token: SECRET}}]",
        "env.kwargs={max_episode_steps: 50}",
        "iterations=2",
    ]
    redacted = redact_command(command)
    assert not any("SECRET" in word or "KEY" in word for word in redacted), redacted
    assert redacted == [
        "torchrun",
        "--nproc-per-node=2",
        "configs/smoke.yaml",
        "--storage",
        "s3://bucket/run",
        "--storage=s3://bucket/run",
        "storage.options={endpoint_url: 'http://127.0.0.1:9000', key: '***', secret: '***'}",
        "storage.options.secret=***",
        "teacher=s3://bucket/teacher",
        "hooks=[{target: 'probe:Hook', kwargs: {token: '***'}}]",
        "env.kwargs={max_episode_steps: 50}",
        "iterations=2",
    ]


def test_credentials_travel_in_the_environment_and_come_back_in_place():
    words = ["c.yaml", "--storage", "s3://AK:SK@b/run", "storage.options.secret=SK", "iterations=3"]
    shown, env = hide_credentials(words)
    assert shown == ["c.yaml", "--storage", "s3://b/run", "storage.options.secret=***", "iterations=3"]
    assert "SK" not in " ".join(shown) and reveal_credentials(shown, env) == words
    assert reveal_credentials(["c.yaml", "iterations=4"], env) == ["c.yaml", "iterations=4"]  # another command line
    assert hide_credentials(["c.yaml", "iterations=3"]) == (["c.yaml", "iterations=3"], {})  # nothing to hide


def test_a_gcs_token_given_as_credentials_loses_its_keys() -> None:
    """gcsfs takes ``token`` as a service account's (or a user's) credentials, a dict: its secrets are hidden and
    known for scrubbing, the rest stays readable."""
    token = {"type": "service_account", "client_email": "ci@p.iam", "private_key": "-----PEM-----"}
    token["private_key_id"] = "ID9"
    options = {"project": "p", "token": {**token, "refresh_token": "RT"}}
    shown = redact_options(options)
    assert shown["project"] == "p" and shown["token"]["client_email"] == "ci@p.iam"
    assert "-----PEM-----" not in str(shown) and "ID9" not in str(shown) and "RT" not in str(shown)
    assert {"-----PEM-----", "ID9", "RT"} <= set(secret_values(options))


def test_a_saved_config_read_back_takes_no_hidden_value_for_a_credential(tmp_path) -> None:
    """``<log_dir>/config.yaml`` holds ``key: '***'``: read back (to go on with the run from anywhere), ``***`` was
    sent to S3 as the key, overriding the environment's own and refused as access denied. A hidden value is no value:
    the credentials come from the environment or ``--storage-option`` again; everything else is kept."""
    options = {"endpoint_url": "http://127.0.0.1:9000", "key": "KEY", "secret": "SECRET", "config_kwargs": {}}
    options["token"] = {"client_secret": "S", "client_id": "id"}  # a gcsfs token given as credentials, key by key
    saved = tmp_path / "config.yaml"
    saved.write_text(yaml.safe_dump({"storage": {"url": "s3://bucket/run", "options": redact_options(options)}}))
    assert HIDDEN in saved.read_text()
    read = load_config(str(saved)).storage.options
    assert read == {"endpoint_url": "http://127.0.0.1:9000", "config_kwargs": {}, "token": {"client_id": "id"}}
    given = load_config(str(saved), ["storage.options.key=K2"]).storage.options
    assert given["key"] == "K2" and "secret" not in given
