"""The run layer: the request, the inputs, the outputs (staging, atomic publish), the summary.

Any process that runs anything imports it, so it points the kernels' front door at their ahead-of-time
build here (:mod:`.aot`; read only when a kernel is first called)."""

from . import aot as _aot

_aot.install()
