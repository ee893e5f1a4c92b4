"""Print to the terminal and a log file at once (the benchmarks' logs)."""


class Tee:
    """A writable stream that writes to every one of *streams*."""

    def __init__(self, *streams):
        self.streams = streams

    def write(self, s):
        for st in self.streams:
            st.write(s)
            st.flush()

    def flush(self):
        for st in self.streams:
            st.flush()


def start_log(log=None) -> None:
    """The benchmarks' log header: stdout also written to *log* (a path,
    its folder made) if given, then the command and the code's version."""
    import subprocess
    import sys
    from pathlib import Path

    if log:
        Path(log).parent.mkdir(parents=True, exist_ok=True)
        sys.stdout = Tee(sys.__stdout__, open(log, "w"))  # noqa: SIM115
    version = subprocess.run(
        ["git", "describe", "--always", "--dirty"], capture_output=True, text=True
    ).stdout.strip()
    print(f"command: {' '.join(sys.argv)}  (code {version})", flush=True)
