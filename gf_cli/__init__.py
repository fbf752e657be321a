"""The ``gf-cli`` command (import name ``gf_cli``): parses arguments, calls ``gf_core``, prints."""
