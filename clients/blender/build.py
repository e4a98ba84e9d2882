#!/usr/bin/env python3
"""Builds the Blender extension's zip: ``python3 clients/blender/build.py [-o DIR]``.

The zip holds ``tessera_blender/`` (the manifest at its root, as the extension format
wants) and the Python client of ``clients/python/tessera_client`` copied in as
``vendor/tessera_client``, so the installed extension needs nothing outside Blender.
Standard library only; prints the zip's path. Blender's own validator checks the result:
``blender --command extension validate tessera-VERSION.zip``.
"""

import argparse
import os
import re
import sys
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
PACKAGE = os.path.join(HERE, "tessera_blender")
CLIENT = os.path.join(HERE, "..", "python", "tessera_client")


def _files(root):
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d not in ("__pycache__", "vendor"))
        for name in sorted(filenames):
            if name.endswith((".pyc", ".pyo")):
                continue
            full = os.path.join(dirpath, name)
            yield full, os.path.relpath(full, root)


def build(out_dir):
    with open(os.path.join(PACKAGE, "blender_manifest.toml")) as f:
        manifest = f.read()
    version = re.search(r'^version\s*=\s*"([^"]+)"', manifest, re.M).group(1)
    ext_id = re.search(r'^id\s*=\s*"([^"]+)"', manifest, re.M).group(1)
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, f"{ext_id}-{version}.zip")
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for full, rel in _files(PACKAGE):
            z.write(full, rel)
        z.writestr("vendor/__init__.py", '"""Packages vendored into the extension."""\n')
        for full, rel in _files(CLIENT):
            z.write(full, os.path.join("vendor", "tessera_client", rel))
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--out", default=os.path.join(HERE, "dist"), help="output directory (default: clients/blender/dist)")
    a = ap.parse_args(argv)
    print(build(a.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
