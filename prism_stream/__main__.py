"""``python -m prism_stream``: the command line."""

from prism_stream_cli.main import run

if __name__ == "__main__":
    run()
