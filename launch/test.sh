#!/usr/bin/env bash
# Set up, lint, then run the whole test suite (real torchrun, real MuJoCo, a real S3 API server on 127.0.0.1).
# Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash launch/setup.sh
.venv/bin/ruff check ftrain tests launch examples
.venv/bin/ruff format --check ftrain tests launch examples
exec .venv/bin/python -m pytest -p no:cacheprovider "$@"
