"""``testbed secret PATH``: a new credentials file for nodes started by hand (one host or several)."""

from __future__ import annotations

import argparse
import json
import sys

from . import cliargs


def add_arguments_secret(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="the new file (0600; never overwritten)")
    cliargs.add_json(p, "the file's path and the user names in it")


def main_secret(args) -> int:
    from .errors import BadInput
    from .io import transport

    cred = transport.Credentials.new()
    try:
        path = cred.write(args.path)
    except FileExistsError:
        raise BadInput(f"{args.path} exists: a secret file is never overwritten") from None
    except OSError as e:
        raise BadInput(f"cannot write {args.path}: {e.strerror or e}") from None
    if args.json:
        print(json.dumps({"path": str(path), "users": sorted(cred.users)}))
    else:
        print(f"wrote {path} (mode 600): one password for each of {', '.join(cred.users)}")
        print("give it to every process of the run: testbed node ROLE SCENARIO --secret-file "
              f"{path} ... (copy it to other hosts over a secure channel, e.g. scp)", file=sys.stderr)
    return 0
