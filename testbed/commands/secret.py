"""``testbed secret PATH``: new credentials for nodes started by hand (one host or several).

``testbed secret PATH``: a 0600 file of one password per process (the router topology).
``testbed secret --tls DIR``: a new 0700 folder with the run's certificate authority
(``ca.pem``; its key is thrown away) and a key and certificate per process (the peer topology).
"""

from __future__ import annotations

import argparse
import json
import sys

from ..common import cliargs


def add_arguments_secret(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="the new file (0600; never overwritten), or with --tls the new folder")
    p.add_argument("--tls", action="store_true",
                   help="TLS certificates for --topology peer: a folder with ca.pem and NAME.pem, NAME.key per process")
    cliargs.add_json(p, "the file's path and the user names in it")


def main_secret(args: argparse.Namespace) -> int:
    from ..common.errors import BadInput
    from ..wire import transport

    if args.tls:
        try:
            tls = transport.TlsCredentials.new(args.path)
        except FileExistsError:
            raise BadInput(f"{args.path} exists: a TLS folder is never overwritten") from None
        except OSError as e:
            raise BadInput(f"cannot make {args.path}: {e.strerror or e}") from None
        if args.json:
            print(json.dumps({"path": str(tls.folder), "users": list(transport.USERS), "tls": True}))
        else:
            print(f"made {tls.folder} (mode 700): the run's certificate authority (ca.pem; its key is gone) and a key "
                  f"and certificate for each of {', '.join(transport.USERS)}")
            print("give it to every process of the run: testbed node ROLE SCENARIO --topology peer --tls-dir "
                  f"{tls.folder} ... (on another host, copy it over a secure channel; a process needs ca.pem and "
                  "its own NAME.pem and NAME.key)", file=sys.stderr)
        return 0
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
