"""A run on Google Cloud Storage (``gs://``), on fake-gcs-server's real GCS JSON API from PyPI: its lease, fence and
manifests rest on ``ifGenerationMatch`` (tests/ckpt/test_cas.py), and a supervised run commits, verifies and resumes
there, and trains what a run on a local directory trains."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from ftrain.ckpt.storage import Storage

from helpers import REPO, child_env, create_gcs_bucket, gcs_options, run_train

pytestmark = pytest.mark.slow


def test_a_run_on_gcs_commits_verifies_resumes_and_trains_what_a_local_one_does(gcs_server, tmp_path, reference_state):
    url, options = f"gs://{create_gcs_bucket(gcs_server)}/run", gcs_options(gcs_server)
    flags = [f"--storage-option={key}={value}" for key, value in options.items()]
    run_train(url, "iterations=4", f"log_dir={tmp_path / 'logs'}", *flags, ranks=2, supervised=True)
    resumed = run_train(url, "iterations=8", f"log_dir={tmp_path / 'logs'}", *flags, ranks=2, supervised=True)
    assert "resumed from step 4" in resumed.stdout, resumed.stdout[-2000:]
    verify = subprocess.run(
        [sys.executable, "-m", "ftrain", "ckpt", "verify", url, *flags],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert verify.returncode == 0, verify.stderr[-3000:]
    storage = Storage.open(url, options)
    newest = max(storage.list_dirs("checkpoints"))
    manifest = json.loads(storage.read(f"checkpoints/{newest}/MANIFEST.json"))
    assert manifest["step"] == 8 and manifest["state_sha256"] == reference_state(8)
