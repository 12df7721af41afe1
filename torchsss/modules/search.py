"""Ray / receiver search in a light-view positions texture (Shah §5.3.4) as an nn.Module.

:class:`NewtonRaphsonSearch` is the module twin of :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect`:
the options (iteration count, update rule, safeguards, tolerances) are fixed when the module is built, the rays,
the texture and the light's matrix come in as tensors, so ``forward()`` compiles and exports to ONNX with the
batch, the ray count and the texture size dynamic.
"""

from __future__ import annotations

from torch import Tensor, nn

from torchsss.ops.newton_raphson import _check_options, newton_raphson_intersect

__all__ = ["NewtonRaphsonSearch"]


class NewtonRaphsonSearch(nn.Module):
    """Distance along each ray to the receivers stored in a light-view positions texture (Shah §5.3.4).

    ``forward(origins, directions, positions_texture, view_proj)`` returns exactly what
    :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect` returns for the same inputs and the options
    given here (see there and its module docstring for the update rules, the safeguards, the lookup conventions
    and the validity rules). The iterations use tensor ops only, so the module differentiates, runs under
    ``torch.compile`` and exports to ONNX; exported, four or more iterations are one ONNX ``Loop`` (the graph and
    the export time do not grow with ``iterations``). No parameters or buffers.

    Args:
        iterations: number of updates of the estimate (>= 0).
        method: ``"shah"`` (Shah's estimator, one lookup per iteration) or ``"newton"`` (Newton-Raphson on the
            signed residual with a forward-difference slope, two lookups).
        fallback: bisect the last two estimates when they bracket the root and the last step did not reduce the
            residual.
        fd_step: relative step of the forward difference (``"newton"``), > 0.
        tol: relative convergence tolerance (>= 0): converged rays stop moving.
        max_residual: if given, rays whose final estimate lies farther than this (mm) from the receiver seen
            through it are invalid.
        return_info: also return the dict of per-ray diagnostics (``"oscillated"``, ``"fallback"``,
            ``"residual"``).

    Shapes:
        - origins: :math:`(B, N, 3)` ray origins (mm).
        - directions: :math:`(B, N, 3)` ray directions (any non-zero length).
        - positions_texture: :math:`(B, 3, H, W)` receiver world positions per light texel (row 0 at the top),
          non-finite = no receiver.
        - view_proj: :math:`(B, 4, 4)` or :math:`(4, 4)` world-to-clip matrix of the light.
        - initial_distance: optional :math:`(B, N)` first estimate :math:`d_0` (mm; default 0).
        - output: ``(distance, valid)``, :math:`(B, N)` distances along the unit directions (mm, 0 where not
          valid) and the :math:`(B, N)` bool validity mask; with ``return_info`` also the dict of :math:`(B, N)`
          diagnostics.

    Raises:
        TypeError: an option of the wrong type.
        ValueError: an unknown ``method`` or an option out of range.

    Examples:
        >>> import torch
        >>> # a light 10 mm above the plane z = 0, looking down (orthographic, 20 mm wide), 4 x 4 texels
        >>> ys, xs = torch.meshgrid(7.5 - 5.0 * torch.arange(4.0), -7.5 + 5.0 * torch.arange(4.0), indexing="ij")
        >>> tex = torch.stack([xs, ys, torch.zeros(4, 4)])[None]  # row 0 at the top (largest y)
        >>> view_proj = torch.tensor([[0.1, 0, 0, 0], [0, 0.1, 0, 0], [0, 0, -0.1, 0], [0, 0, 0, 1.0]])
        >>> search = NewtonRaphsonSearch(2, "newton")
        >>> d, ok = search(torch.tensor([[[0.0, 0.0, 4.0]]]), torch.tensor([[[0.6, 0.0, -0.8]]]), tex, view_proj)
        >>> round(d.item(), 4), ok.item()  # exact hit at d = 4 / 0.8 = 5
        (5.0, True)
    """

    def __init__(
        self,
        iterations: int = 5,
        method: str = "shah",
        *,
        fallback: bool = True,
        fd_step: float = 1e-3,
        tol: float = 1e-5,
        max_residual: float | None = None,
        return_info: bool = False,
    ) -> None:
        super().__init__()
        _check_options(iterations, method, fallback, fd_step, tol, max_residual, return_info)
        self.iterations = int(iterations)
        self.method = method
        self.fallback = fallback
        self.fd_step = float(fd_step)
        self.tol = float(tol)
        self.max_residual = None if max_residual is None else float(max_residual)
        self.return_info = return_info

    def forward(
        self,
        origins: Tensor,
        directions: Tensor,
        positions_texture: Tensor,
        view_proj: Tensor,
        initial_distance: Tensor | None = None,
    ) -> tuple[Tensor, Tensor] | tuple[Tensor, Tensor, dict[str, Tensor]]:
        """Search the receivers along the rays; see the class docstring for shapes and outputs.

        Raises:
            TypeError, ValueError: as :func:`~torchsss.ops.newton_raphson.newton_raphson_intersect` (non-tensor
                or non-floating inputs, wrong shapes, different devices, a non-finite ``view_proj``).
        """
        return newton_raphson_intersect(
            origins, directions, positions_texture, view_proj, self.iterations, self.method,
            fallback=self.fallback, initial_distance=initial_distance, fd_step=self.fd_step, tol=self.tol,
            max_residual=self.max_residual, return_info=self.return_info,
        )

    def extra_repr(self) -> str:
        """The options, for ``repr``."""
        extra = "" if self.max_residual is None else f", max_residual={self.max_residual}"
        return (f"iterations={self.iterations}, method={self.method!r}, fallback={self.fallback}, "
                f"fd_step={self.fd_step}, tol={self.tol}{extra}, return_info={self.return_info}")
