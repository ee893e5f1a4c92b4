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
