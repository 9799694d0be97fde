"""Mixed precision of the learners: `agent.precision` "f32" or "bf16" (docs/learner.md, "Precision").

Under "bf16" every dense layer multiplies bfloat16 copies of its input and kernel and accumulates in
float32, forward and backward, as DreamerV2's and PEG's `precision: 16` did with float16. Everything else
stays float32: parameters and their gradients, optimizer state, biases, activations between layers,
LayerNorm, distributions, losses, returns and the RSSM state carried across steps.

    dense = nn.Dense(..., dot_general=dot_general_for("bf16"))
    y = matmul(x, kernel, "bf16")                  # (..., in) @ (in, out) -> float32 (..., out)

Why the backward pass is written out (`_bf16_matmul`'s vjp): JAX's transpose of a bfloat16 dot with a
float32 result multiplies the float32 cotangent by a bfloat16 operand, which XLA's CPU backend runs as a
float32 matmul; casting the cotangent to bfloat16 first keeps both backward matmuls (two thirds of the
FLOPs) in bfloat16 with float32 accumulation. A bfloat16 result (instead of float32 accumulation) is no
faster on CPU and loses precision (docs/performance.md, "Precision").
"""

from __future__ import annotations

import json
import pathlib

import jax
import jax.numpy as jnp

from morefree_jax.legacy import stored_value

PRECISIONS = ("f32", "bf16")
CHOICES = ("auto", *PRECISIONS)  # "auto": default_precision() of the machine the run starts on
BF16_CPU_FLAGS = (" avx512_bf16", " amx_bf16")  # /proc/cpuinfo flags of CPUs with bfloat16 dot products


def check_precision(precision: str, choices: tuple[str, ...] = PRECISIONS) -> str:
    if precision not in choices:
        raise ValueError(f"unknown precision {precision!r}; valid: {', '.join(choices)}")
    return precision


def _cpu_has_bf16() -> bool:
    try:
        with open("/proc/cpuinfo") as file:
            flags = file.read()
    except OSError:
        return False
    return any(flag in flags for flag in BF16_CPU_FLAGS)


def cpu_precision(precision: str = "auto") -> str:
    """The concrete precision of `precision` on this machine's CPU, without starting JAX: "auto" is "bf16" on
    CPUs with bfloat16 dot products (AVX512-BF16, AMX), else "f32"."""
    check_precision(precision, CHOICES)
    if precision != "auto":
        return precision
    return "bf16" if _cpu_has_bf16() else "f32"


def default_precision() -> str:
    """"bf16" on accelerators, cpu_precision() on CPUs: the faster one by the whole-run benchmark
    (docs/performance.md, "Precision"). Starts JAX's backend: call it after runtime.configure()."""
    import jax

    return "bf16" if jax.default_backend() != "cpu" else cpu_precision()


def stored_precision(run_dir) -> str | None:
    """agent.precision in a run dir's config.json ("f32" in one written before the option: those runs
    computed in float32: legacy.py); None where there is no config.json yet."""
    path = pathlib.Path(run_dir) / "config.json"
    if not path.exists():
        return None
    return stored_value(json.loads(path.read_text()), "agent.precision")


def resolve_precision(precision: str) -> str:
    """A concrete precision ("f32" or "bf16") for a config value that may be "auto"."""
    check_precision(precision, CHOICES)
    return default_precision() if precision == "auto" else precision


def _contract_last(lhs: jax.Array, rhs: jax.Array, lhs_axis: int, rhs_axis: int) -> jax.Array:
    """lhs contracted with rhs over one axis each, in bfloat16 with a float32 result."""
    dims = (((lhs_axis % lhs.ndim,), (rhs_axis % rhs.ndim,)), ((), ()))
    return jax.lax.dot_general(lhs.astype(jnp.bfloat16), rhs.astype(jnp.bfloat16), dims,
                               preferred_element_type=jnp.float32)


@jax.custom_vjp
def _bf16_matmul(x: jax.Array, kernel: jax.Array) -> jax.Array:
    return _contract_last(x, kernel, -1, 0)


def _bf16_matmul_fwd(x, kernel):
    x16, kernel16 = x.astype(jnp.bfloat16), kernel.astype(jnp.bfloat16)
    return _contract_last(x16, kernel16, -1, 0), (x16, kernel16)


# Narrower weight gradients keep XLA's own dot: its library (YNNPACK) takes no vector operands and such a
# product is cheap; from 8 on, every shape tried (8 to 384 columns, 16 to 800 rows) ran in the library.
MIN_LIBRARY_WIDTH = 8


def _row_major_transpose(matrix: jax.Array) -> jax.Array:
    """matrix.T stored row-major. XLA gives a plain transpose a column-major layout and folds it into the
    dot, and its CPU backend runs a dot whose lhs contracts over the major axis as a float32 matmul (the
    library kernels take only row-major operands); flattening behind an optimization barrier makes the
    transposed copy real."""
    flat = jax.lax.optimization_barrier(matrix.T.reshape(-1))
    return flat.reshape(matrix.shape[1], matrix.shape[0])


def _weight_gradient(x16: jax.Array, grad16: jax.Array) -> jax.Array:
    """(N, in) x (N, out) -> (in, out), contracted over the N rows in bfloat16 with a float32 result. The
    smaller of the two is transposed into a row-major lhs (docs/performance.md, "Precision"). Below
    MIN_LIBRARY_WIDTH columns XLA's own dot runs it, which needs no transpose."""
    if min(x16.shape[-1], grad16.shape[-1]) < MIN_LIBRARY_WIDTH:
        return _contract_last(x16, grad16, 0, 0)
    if x16.shape[-1] <= grad16.shape[-1]:
        return _contract_last(_row_major_transpose(x16), grad16, -1, 0)
    transposed = _contract_last(_row_major_transpose(grad16), x16, -1, 0)  # (out, in)
    # without the barrier XLA folds the .T into the dot as a column-major result, which the library refuses
    # after bfloat16 was kept for it: the CPU runtime then fails ("Unsupported element type for DotThunk")
    return jax.lax.optimization_barrier(transposed).T


def _bf16_matmul_bwd(residuals, grad):
    """Gradients in float32, the dtype of every input here (parameters and activations)."""
    x16, kernel16 = residuals
    grad16 = grad.astype(jnp.bfloat16)
    grad_x = _contract_last(grad16, kernel16, -1, 1)  # (..., out) x (in, out) -> (..., in)
    flat_x, flat_grad = x16.reshape(-1, x16.shape[-1]), grad16.reshape(-1, grad16.shape[-1])
    return grad_x, _weight_gradient(flat_x, flat_grad)


_bf16_matmul.defvjp(_bf16_matmul_fwd, _bf16_matmul_bwd)


def matmul(x: jax.Array, kernel: jax.Array, precision: str = "f32") -> jax.Array:
    """x (..., in) @ kernel (in, out) at the given precision; float32 in, float32 out."""
    if precision == "bf16":
        return _bf16_matmul(x, kernel)
    return x @ kernel


def _bf16_dot_general(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None, **_):
    """A drop-in for lax.dot_general in nn.Dense (contracts the input's last axis with the kernel's first)."""
    (lhs_contract, rhs_contract), (lhs_batch, rhs_batch) = dimension_numbers
    dense_layout = (tuple(lhs_contract) == (lhs.ndim - 1,) and tuple(rhs_contract) == (0,)
                    and not lhs_batch and not rhs_batch and rhs.ndim == 2)
    if not dense_layout:
        raise ValueError(f"bf16 dot_general supports nn.Dense's layout only, got {dimension_numbers}")
    return _bf16_matmul(lhs, rhs)


def dot_general_for(precision: str):
    """The `dot_general` argument of nn.Dense for `precision` (None: lax.dot_general, float32)."""
    return _bf16_dot_general if check_precision(precision) == "bf16" else None
