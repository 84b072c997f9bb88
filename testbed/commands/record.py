"""``testbed record SCENARIO``: record a live run to MCAP (``testbed.nodes.recorder``), its flags.

``testbed run`` starts its recorder with these flags (``RecorderConfig.argv``)."""

from __future__ import annotations

import argparse

from ..common import optionspec
from ..nodes.options import RecorderConfig, add_run_option_arguments
from ..wire.session import add_zenoh_arguments
from .liveconfig import recorder_config


def add_arguments_record(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="the run's scenario (file or bundled name): stored in the recording")
    optionspec.add_arguments(p, RecorderConfig, "record")
    add_run_option_arguments(p)
    add_zenoh_arguments(p)


def main_record(args: argparse.Namespace) -> int:
    from ..nodes.recorder import run_recorder

    return run_recorder(recorder_config(args))
