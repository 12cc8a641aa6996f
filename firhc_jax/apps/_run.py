"""The run skeleton of the closed-loop applications (``example``, ``hopper``, ``tanks``, ``inverter``).

Each application is a small module with one ``App`` subclass that fills in
the contract: its arguments, its option checks, its closed loop
(``simulate``), its ``summary.json`` record (``summarize``), its figures
(``plot``) and its report line (``report``). The skeleton does the rest, the
same way for every application: the subcommand with ``--out`` and
``--no-progress``, float64, the output folder, and one stage line on stderr
(``_status.stage``) while it writes ``summary.json``, ``closed_loop.npz``
(``fj.ClosedLoop.load`` reads it) and the figures; then it prints the report
and what it wrote. Compiling and timing the loop is ``_timing.timed_closed_loop``,
which the applications' ``simulate`` call.
"""
from __future__ import annotations

import abc
import argparse
import functools
import json
from pathlib import Path

import jax

from ._args import output_dir
from ._status import stage


class App(abc.ABC):
    """One command. ``simulate`` returns the run: any object with the closed loop as ``.loop``
    (``fj.ClosedLoop``), which the other methods receive back."""

    name: str  # the subcommand
    help: str  # its line in ``python -m firhc_jax --help``
    description: str  # the top of its own ``--help``
    formatter_class = argparse.HelpFormatter

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """The command's own options (``--out`` and ``--no-progress`` are the skeleton's; default: none)."""
        return

    def variant(self, args) -> App:
        """The ``App`` that runs these options (default: this one): one command, several closed loops."""
        return self

    def check(self, parser: argparse.ArgumentParser, args) -> None:
        """Refuse options that do not fit together with ``parser.error``, before any work (default: none)."""
        return

    def default_out(self, args) -> str:
        """The output folder when ``--out`` is not given (default ``out/<name>``; a variant may have its own)."""
        return f"out/{self.name}"

    @abc.abstractmethod
    def simulate(self, args):
        """Run the closed loop (float64 is on, ``args.out`` exists); return the run."""

    @abc.abstractmethod
    def summarize(self, args, run) -> dict:
        """The ``summary.json`` record of ``run``."""

    @abc.abstractmethod
    def plot(self, args, run, summary: dict) -> list[Path]:
        """Write the figures into ``args.out``; return their paths."""

    @abc.abstractmethod
    def report(self, args, summary: dict) -> str:
        """The lines printed on stdout after the run."""

    def exit_status(self, summary: dict) -> int:
        """The command's exit status (default 0)."""
        return 0

    def register(self, subparsers) -> argparse.ArgumentParser:
        """Add the subcommand, its options and the skeleton's ``--out`` and ``--no-progress``."""
        parser = subparsers.add_parser(self.name, help=self.help, description=self.description,
                                       formatter_class=self.formatter_class)
        self.add_arguments(parser)
        parser.add_argument("--out", type=output_dir, default=None, metavar="DIR",
                            help=f"output folder (default {self.out_help})")
        parser.add_argument("--no-progress", action="store_true", help="no progress bar")
        parser.set_defaults(func=self.run, check=functools.partial(self._check, parser))
        return parser

    @property
    def out_help(self) -> str:
        """``--out``'s default, as its help names it."""
        return f"out/{self.name}"

    def _check(self, parser: argparse.ArgumentParser, args) -> None:
        """``--out`` of the variant that runs, when not given (checked as a given one is), then ``check``."""
        if args.out is None:
            default = self.variant(args).default_out(args)
            try:
                args.out = output_dir(default)
            except argparse.ArgumentTypeError as e:
                parser.error(f"argument --out: {e}")
        self.check(parser, args)

    def run(self, args) -> int:
        """Simulate, write ``summary.json``, ``closed_loop.npz`` and the figures, report; the exit status."""
        app = self.variant(args)
        jax.config.update("jax_enable_x64", True)
        out = Path(args.out if args.out is not None else app.default_out(args))
        args.out = out
        out.mkdir(parents=True, exist_ok=True)
        run = app.simulate(args)
        summary = app.summarize(args, run)
        with stage(f"writing summary.json, closed_loop.npz and the figures to {out}"):
            (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
            run.loop.save(out / "closed_loop.npz")
            figures = app.plot(args, run, summary)
        print(app.report(args, summary))
        print(f"wrote {out / 'summary.json'}, {out / 'closed_loop.npz'} and {', '.join(str(f) for f in figures)}")
        return app.exit_status(summary)
