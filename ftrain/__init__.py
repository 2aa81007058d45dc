"""ftrain: distributed, fault-tolerant PPO training on CPU."""

import os

# rsl_rl imports GitPython, which refuses to import where no git binary exists unless told to stay quiet.
os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
