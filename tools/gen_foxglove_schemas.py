"""Write the Foxglove schemas a recording uses, as published by foxglove-sdk, into the package.

    pip install 'foxglove-sdk>=0.30,<0.31' && python tools/gen_foxglove_schemas.py

Each file is the schema's serialized ``FileDescriptorSet`` exactly as
``foxglove.messages.<Name>.get_schema().data`` gives it, so a recording written
without foxglove-sdk installed carries the same schemas (a test compares them).
"""

from __future__ import annotations

from pathlib import Path

OUT = Path(__file__).resolve().parents[1] / "testbed" / "view" / "foxglove_schemas"
NAMES = ("Log", "SceneUpdate")


def main() -> None:
    import foxglove.messages as fm

    for name in NAMES:
        s = getattr(fm, name).get_schema()
        assert s.encoding == "protobuf" and s.name == f"foxglove.{name}", (s.name, s.encoding)
        (OUT / f"foxglove.{name}.fds").write_bytes(s.data)
        print(f"{OUT / f'foxglove.{name}.fds'}: {len(s.data)} bytes")


if __name__ == "__main__":
    main()
