"""The ``mmslam`` command line: a thin layer over the library API.

Each subpackage owns its commands in its own ``cli.py`` (``register(app)``); heavy imports
(Sionna, matplotlib) happen inside the commands, so ``mmslam --help`` is fast.
User errors (:class:`~mmslam.errors.MmslamError`) print one line ``error: ...`` and exit non-zero.
"""
from __future__ import annotations

import sys

import typer

from mmslam.errors import MmslamError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Ray-traced mmWave multipath datasets and cooperative MM-PHD-SLAM.")


def _register_all() -> None:
    from mmslam.pipelines import cli as pipelines_cli
    from mmslam.raytrace import cli as raytrace_cli
    from mmslam.scenes import cli as scenes_cli
    from mmslam.slam import cli as slam_cli

    scenes_cli.register(app)
    raytrace_cli.register(app)
    slam_cli.register(app)
    pipelines_cli.register(app)


_register_all()


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit code (2 for user errors)."""
    try:
        app(args=argv, standalone_mode=False)
    except MmslamError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted; finished work is kept, re-run to resume", file=sys.stderr)
        return 130
    except SystemExit as e:  # typer/click usage errors and --help
        return int(e.code or 0)
    except Exception as e:  # click's own usage errors in non-standalone mode
        import click

        if isinstance(e, click.exceptions.ClickException):
            e.show()
            return 2
        if isinstance(e, click.exceptions.Abort):
            return 1
        raise
    return 0


if __name__ == "__main__":
    sys.exit(main())
