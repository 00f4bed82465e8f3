"""The run layer: the request, the inputs, the outputs (staging, atomic publish), the summary."""
