"""Build the test FMU of the Lienard plant (``lienard.c`` + ``modelDescription.xml``) into a .fmu file.

gcc compiles the C source against the FMI 2.0 headers that fmpy ships in
``fmpy/c-code``; the archive holds ``modelDescription.xml`` and
``binaries/linux64/lienard.so``.  ``python tests/data/fmu/build.py OUT.fmu`` builds one by hand.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent


def fmi_headers() -> Path:
    import fmpy

    return Path(fmpy.__file__).resolve().parent / "c-code"


def build(out: str | Path, *, model_description: str | None = None, with_binary: bool = True) -> Path:
    """Compile and zip the FMU into ``out``; ``model_description`` replaces the XML text (broken FMUs)."""
    import fmpy

    out = Path(out)
    cc = shutil.which("gcc") or shutil.which("cc")
    if cc is None:
        raise RuntimeError("no C compiler (gcc) to build the test FMU")
    with tempfile.TemporaryDirectory(prefix="testbed-fmu-build-") as d:
        so = Path(d) / "lienard.so"
        if with_binary:
            subprocess.run([cc, "-shared", "-fPIC", "-O2", "-std=c99", "-Wall", "-I", str(fmi_headers()),
                            str(HERE / "lienard.c"), "-o", str(so), "-lm"], check=True, capture_output=True,
                           text=True)
        out.parent.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as z:
            z.writestr("modelDescription.xml", model_description if model_description is not None else
                       (HERE / "modelDescription.xml").read_text())
            if with_binary:
                z.write(so, f"binaries/{fmpy.platform}/lienard.so")
    return out


def variant(src: str | Path, out: str | Path, *, model_description: str | None = None, binary: bytes | None = None,
            drop_binary: bool = False) -> Path:
    """A copy of the built FMU ``src`` with its XML text or binary replaced (or the binary left out)."""
    out = Path(out)
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            data = zin.read(item)
            if item.filename == "modelDescription.xml" and model_description is not None:
                data = model_description.encode()
            elif item.filename.startswith("binaries/"):
                if drop_binary:
                    continue
                if binary is not None:
                    data = binary
            zout.writestr(item.filename, data)
    return out


if __name__ == "__main__":  # pragma: no cover
    print(build(sys.argv[1] if len(sys.argv) > 1 else "lienard.fmu"))
