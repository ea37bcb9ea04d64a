"""Subcommands of the `meshseal` command line (see meshseal.cli)."""
