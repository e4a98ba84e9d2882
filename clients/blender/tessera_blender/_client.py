"""The Python client (clients/python/tessera_client), vendored into the extension's zip
as ``vendor/tessera_client`` by clients/blender/build.py; from a source checkout
(``clients/blender`` on ``sys.path``) the repository's copy is used, so there is one copy
of the client in the repository."""

import os
import sys

try:
    from .vendor import tessera_client  # noqa: F401  (the built extension)
except ImportError:
    _repo_client = os.path.join(
        os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "python"
    )
    if os.path.isdir(os.path.join(_repo_client, "tessera_client")) and _repo_client not in sys.path:
        sys.path.append(_repo_client)
    import tessera_client  # noqa: F401
