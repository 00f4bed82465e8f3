"""The run layer: the request, the inputs, the outputs (staging, atomic publish), the summary."""

# the command line of this process when the `prism-stream` command runs it (recorded in provenance);
# None when prism_stream is called from Python
COMMAND_LINE: tuple | None = None
