"""Where the model shipped with topseg lies, and the help text of every `--model` option.

Kept apart from the Segmenter so that reading `--help` loads no numba kernel module.
"""

from __future__ import annotations

import sys
from pathlib import Path

from topseg.core.errors import TopsegError

#: Where `deploy/install.sh` puts the bundled model (below its --root).
INSTALLED_MODEL = Path("/opt/topseg/models/default.npz")
#: The bundled model inside a checkout, relative to its root.
CHECKOUT_MODEL = Path("models") / "default.npz"
#: Help text for `--model` of every command that defaults to the bundled model.
MODEL_HELP = (
    "model file from `topseg train` (default: the bundled model, models/default.npz of "
    "the checkout, or /opt/topseg/models/default.npz when installed with deploy/install.sh)"
)


def bundled_model_path() -> Path:
    """The bundled model: the checkout's `models/default.npz`, else the installed copy.

    The installed copy is found beside the venv that runs topseg (`install.sh` puts the venv
    at PREFIX/venv and the model at PREFIX/models/), else at /opt/topseg. A TopsegError
    (one line) when there is none.
    """
    candidates = [
        Path(__file__).resolve().parents[1] / CHECKOUT_MODEL,  # core/ -> the checkout root
        Path(sys.prefix).resolve().parent / CHECKOUT_MODEL,  # PREFIX/venv -> PREFIX/models
        INSTALLED_MODEL,
    ]
    for path in candidates:
        if path.is_file():
            return path
    raise TopsegError(
        f"no bundled model (looked for {', '.join(map(str, dict.fromkeys(candidates)))}); "
        "name one with --model"
    )
