"""`python -m tisem COMMAND ...` is the `tisem` command."""

from tisem.commands import console

if __name__ == "__main__":
    console()
