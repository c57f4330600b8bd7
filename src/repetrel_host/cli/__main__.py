"""``python -m repetrel_host.cli``: hyrel-send."""

from repetrel_host.cli.app import main

if __name__ == "__main__":  # run, not imported (the wheel's test imports every module)
    main()
