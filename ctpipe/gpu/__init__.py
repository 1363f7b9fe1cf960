"""Where ctpipe's heavy kernels run: the CPU, or a CUDA GPU when there is one.

The public face of :mod:`ctpipe._shared.device` (see there for how a device is chosen), and
:mod:`ctpipe.gpu.check`, which compares every GPU kernel with its CPU twin.

Examples
--------
>>> from ctpipe import gpu
>>> with gpu.use("cpu"):
...     gpu.active()
'cpu'
"""

from ctpipe._shared.device import DEVICES, Selection, active, check_device, requested, select, set_default, use

__all__ = ["DEVICES", "Selection", "active", "check_device", "requested", "select", "set_default", "use"]
