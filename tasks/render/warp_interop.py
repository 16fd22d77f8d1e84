"""Zero-copy hand-over of torch tensors to NVIDIA Warp kernels on the tensors' device (CPU or CUDA)."""

import torch
import warp as wp

wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)   # no init banner, no compile notices


def warp_view(tensor: torch.Tensor, dtype=None):
    """A kernel argument sharing the memory of a contiguous tensor (detached: Warp never sees torch's autograd);
    the light ctype form of ``wp.from_torch``, valid for ``launch`` only."""
    wp.init()   # no-op once Warp is up
    return wp.from_torch(tensor.detach(), dtype=dtype, return_ctype=True)


def launch(kernel, dim, inputs: list, device: torch.device, outputs: list | None = None,
           adj_inputs: list | None = None, adj_outputs: list | None = None) -> None:
    """Launch on the Warp device of ``device`` (on torch's current stream on a GPU); with adj_inputs, the kernel's
    generated adjoint (inputs and outputs as in the forward launch, then their adjoints)."""
    stream = wp.stream_from_torch(device) if device.type == "cuda" else None
    wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs or [], adj_inputs=adj_inputs or [],
              adj_outputs=adj_outputs or [], adjoint=adj_inputs is not None, device=wp.device_from_torch(device),
              stream=stream)
