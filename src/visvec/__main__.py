"""`python -m visvec`: the same as the `visvec` command."""

from visvec.cli.main import main

if __name__ == "__main__":
    main()
