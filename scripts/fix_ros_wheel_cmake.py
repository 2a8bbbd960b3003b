"""Point the ROS wheels' exported CMake files at this Python's headers (run by scripts/setup.sh after pip).

The ros-jazzy-* wheels' `*Export.cmake` files name the include directories of the machine that built them
(/opt/python/cp3XX-cp3XX/...: Python's headers and numpy's), so building any interface package against them fails
with "Imported target ... includes non-existent path". This rewrites those paths to this interpreter's include
directory and numpy's, in place; running it again changes nothing.
"""

from __future__ import annotations

import re
import sys
import sysconfig
from pathlib import Path

import numpy

BUILDER = re.compile(r"/opt/python/cp3\d+-cp3\d+/(include/python3\.\d+|lib/python3\.\d+/site-packages/numpy/_core/include)")


def fix(prefix: Path) -> int:
    """Rewrite every exported CMake file under prefix/share; the number of files changed."""
    here = {"include": sysconfig.get_paths()["include"], "numpy": numpy.get_include()}
    changed = 0
    for path in (prefix / "share").glob("*/cmake/*Export.cmake"):
        text = path.read_text()
        new = BUILDER.sub(lambda m: here["numpy"] if "numpy" in m.group(1) else here["include"], text)
        if new != text:
            path.write_text(new)
            changed += 1
    return changed


if __name__ == "__main__":
    n = fix(Path(sys.prefix))
    print(f"ROS wheels' CMake exports pointed at this Python: {n} file(s) changed")
