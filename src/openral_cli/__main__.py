"""``python -m openral_cli``: the same as the ``openral`` command."""

from openral_cli.main import main

main()
