"""Architectures and algorithms from a user's own code, by name in every command.

A plugin is a module that registers something when it is imported (`torch_kitchen.models.register_architecture`,
`trainers.algorithms.register_algorithm`). `kitchen-train`, `kitchen-distill`, `kitchen-eval` and `kitchen-sweep`
import the modules named with `--import MODULE` (found from the working directory too) and every module an
installed package names in the entry-point group `infinite_kitchen.plugins`:

    # pyproject.toml of your package
    [project.entry-points."infinite_kitchen.plugins"]
    my_models = "my_package.models"

The modules imported are kept in the environment (`PLUGINS_VARIABLE`), so a sweep's jobs, in other processes or
on a cluster, import them too.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from importlib.metadata import entry_points
from typing import Sequence

ENTRY_POINTS = "infinite_kitchen.plugins"
PLUGINS_VARIABLE = "INFINITE_KITCHEN_PLUGINS"  # the --import modules, comma-separated, for child processes


class PluginError(ImportError):
    """A plugin that could not be imported, with the module and the reason in one line."""


def add_plugin_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--import", dest="plugins", action="append", default=[], metavar="MODULE",
                        help="a module of yours that registers an architecture or algorithm (repeatable)")


def import_plugins(modules: Sequence[str] = ()) -> list[str]:
    """Imports the entry-point group's plugins, the modules in the environment's `PLUGINS_VARIABLE` and `modules`;
    returns the modules imported. A module that fails to import raises `PluginError` naming it."""
    inherited = [name for name in os.environ.get(PLUGINS_VARIABLE, "").split(",") if name]
    named = list(dict.fromkeys([*inherited, *modules]))
    if named and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # `--import my_module` finds ./my_module.py, as `python -m` would
    imported = []
    for entry in entry_points(group=ENTRY_POINTS):
        _import(entry.value, f"the {ENTRY_POINTS} entry point {entry.name!r}")
        imported.append(entry.value)
    for name in named:
        _import(name, f"--import {name}")
        imported.append(name)
    if named:
        os.environ[PLUGINS_VARIABLE] = ",".join(named)
    return imported


def _import(module: str, source: str) -> None:
    try:
        importlib.import_module(module)
    except Exception as error:  # a plugin's own error is the user's to see, in one line
        reason = f"{type(error).__name__}: {error}".splitlines()[0]
        raise PluginError(f"{source}: cannot import {module!r} ({reason})") from None
