"""``python -m pmdsim``: the ``pmdsim`` command (same as the console script)."""

from pmdsim.cli import main

if __name__ == "__main__":
    main(prog_name="pmdsim")
