"""Build the avflow QGIS plugin zip for QGIS's Plugins > Manage and Install Plugins >
Install from ZIP.

    python qgis/build_plugin.py              # -> build/avflow_qgis-<version>.zip
    python qgis/build_plugin.py -o out/      # another folder

Any Python 3 runs it (standard library only). The zip holds one folder, avflow_qgis/, as
QGIS wants it; bytecode and editor files are left out.
"""

import argparse
import configparser
import os
import sys
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
PLUGIN = HERE / "avflow_qgis"
SKIP_DIRS = {"__pycache__", ".pytest_cache"}
SKIP_SUFFIXES = {".pyc", ".pyo", ".orig", ".rej", ".swp"}


def build(out_dir: Path) -> Path:
    meta = configparser.ConfigParser()
    meta.read(PLUGIN / "metadata.txt", encoding="utf-8")
    version = meta["general"]["version"]
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"avflow_qgis-{version}.zip"
    tmp = target.with_name(target.name + ".tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as zf:
        for root, dirs, files in os.walk(PLUGIN):
            dirs[:] = sorted(d for d in dirs if d not in SKIP_DIRS)
            for name in sorted(files):
                path = Path(root) / name
                if path.suffix in SKIP_SUFFIXES or name.startswith("."):
                    continue
                zf.write(path, Path("avflow_qgis") / path.relative_to(PLUGIN))
    os.replace(tmp, target)  # never a half-written zip
    return target


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(HERE.parent / "build"),
                        help="folder of the zip (default: build/)")
    args = parser.parse_args(argv)
    target = build(Path(args.output))
    print(f"wrote {target} ({target.stat().st_size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
