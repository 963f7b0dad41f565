"""Verbs of the maglev-ros command, one module each (see maglev_ros.cli)."""
