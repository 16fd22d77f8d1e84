"""Zero-copy hand-over of torch tensors to NVIDIA Warp kernels on the tensors' device (CPU or CUDA), with little
per-call Python: array descriptors are cached by what they describe and CPU launches are replayed from recorded
commands (a renderer frame makes ~8 launches with ~80 array arguments; packing them anew cost ~1-2 ms a frame under load)."""

import math
import threading

import torch
import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)   # no init banner, no compile notices

_VIEWS: dict = {}          # (address, shape, strides, torch dtype, device, warp dtype) -> array descriptor
_VIEWS_MAX = 4096          # cleared when full: the renderer's working set is ~100 descriptors
_COMMANDS: dict = {}       # (kernel, adjoint, torch device, thread) -> (recorded wp.Launch, its dim) (CPU)
_SCRATCH: dict = {}        # (name, dtype, device, thread) -> flat work buffer (power-of-two elements)
_SCRATCH_MAX = 64          # cleared when full: the renderer uses ~10 per image size


def warp_view(tensor: torch.Tensor, dtype=None):
    """A kernel argument sharing the memory of a contiguous tensor (detached: Warp never sees torch's autograd);
    the light ctype form of ``wp.from_torch``, valid for ``launch`` only.  A descriptor is only the address, shape,
    strides and type of the memory, so one is reused for any tensor with the same ones.  It does not keep the tensor
    alive: the caller must hold the tensor until the launch has run (no ``warp_view(t.contiguous())``)."""
    key = (tensor.data_ptr(), tensor.shape, tensor.stride(), tensor.dtype, tensor.device, dtype)
    view = _VIEWS.get(key)
    if view is None:
        if len(_VIEWS) >= _VIEWS_MAX:
            _VIEWS.clear()
        wp.init()   # no-op once Warp is up
        view = _VIEWS[key] = wp.from_torch(tensor.detach(), dtype=dtype, return_ctype=True)
        view._ref = view._gradref = None   # the cache holds no tensor alive: the caller keeps its tensors
    return view


def scratch(name: str, shape: tuple, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """An uninitialised work buffer of ``shape`` for memory that kernels write and read inside one call and no
    caller sees (not a returned or saved tensor): a view of the same memory for every call of the same name on the
    calling thread, grown to the next power of two of the elements asked for (a frame's instance count varies from
    frame to frame: a buffer per shape would pile up)."""
    key = (name, dtype, device, threading.get_ident())
    size = math.prod(shape)
    buffer = _SCRATCH.get(key)
    if buffer is None or len(buffer) < size:
        if buffer is None and len(_SCRATCH) >= _SCRATCH_MAX:
            _SCRATCH.clear()
        buffer = _SCRATCH[key] = torch.empty(1 << max(size - 1, 0).bit_length(), dtype=dtype, device=device)
    return buffer[:size].view(shape)


def launch(kernel, dim, inputs: list, device: torch.device, outputs: list | None = None,
           adj_inputs: list | None = None, adj_outputs: list | None = None) -> None:
    """Launch on the Warp device of ``device`` (on torch's current stream on a GPU); with adj_inputs, the kernel's
    generated adjoint (inputs and outputs as in the forward launch, then their adjoints).  Arrays are
    ``warp_view``s or None (a null array); on the CPU the launch replays a recorded command with the new
    arguments written into it."""
    if 0 in (dim if isinstance(dim, tuple) else (dim,)):
        return   # no threads (e.g. every Gaussian culled); Warp records no command for an empty launch
    adjoint = adj_inputs is not None
    args = inputs + (outputs or [])
    adj_args = (adj_inputs or []) + (adj_outputs or [])
    if device.type == "cuda":
        wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs or [], adj_inputs=adj_inputs or [],
                  adj_outputs=adj_outputs or [], adjoint=adjoint, device=wp.device_from_torch(device),
                  stream=wp.stream_from_torch(device))
        return
    key = (kernel, adjoint, device, threading.get_ident())   # per thread: a command holds its arguments
    command, last_dim = _COMMANDS.get(key, (None, None))
    if command is None:
        command = wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs or [], adj_inputs=adj_inputs or [],
                            adj_outputs=adj_outputs or [], adjoint=adjoint, device=wp.device_from_torch(device),
                            record_cmd=True)
    else:
        if last_dim != dim:
            command.set_dim(dim)
        for adjoint_part, values in ((False, args), (True, adj_args)):
            for i, value in enumerate(values):
                if value is None:   # a null array (or a scalar's adjoint)
                    command.set_param_at_index(i, value, adjoint_part)
                else:
                    command.set_param_at_index_from_ctype(i, value, adjoint_part)
    _COMMANDS[key] = command, dim
    command.launch()
