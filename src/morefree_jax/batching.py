"""`lazy_cond`: a `lax.cond` that stays lazy when the run is vmapped over seeds.

Under `jax.vmap` a `lax.cond` whose predicate differs per batch element becomes a select: both branches
run for every element. For the goal search (a third of a `cpu` chunk) that would make every seed search
on every chunk. `lazy_cond` has its own batching rule instead: the expensive branch runs (vmapped) only
when at least one element needs it, and each element keeps its own branch's result. Unbatched it is a
plain `lax.cond`, so a single-seed run computes exactly what it computed before.

Cost under vmap: when some but not all seeds need the branch, it runs for all of them (the extra work is
measured in `make bench`, rows `seeds/*`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import custom_batching


def _hoisted(fn, operands):
    """fn as a function of (operands, consts), with every value it closes over (traced ones included,
    integers and keys too) passed in explicitly: a custom_vmap function must not close over batched
    values. (jax.closure_convert hoists only values that AD could perturb, not integers or keys.)"""
    closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*operands)
    out_tree = jax.tree.structure(out_shape)

    def converted(operands, consts):
        flat = jax.core.eval_jaxpr(closed.jaxpr, consts, *jax.tree.leaves(operands))
        return jax.tree.unflatten(out_tree, flat)

    return converted, list(closed.consts)


def _select(pred, on_true, on_false):
    """Per batch element (leading axis): on_true where pred, else on_false."""
    def pick(a, b):
        return jnp.where(pred.reshape(-1, *[1] * (a.ndim - 1)), a, b)

    return jax.tree.map(pick, on_true, on_false)


def lazy_cond(pred, true_fn, false_fn, *operands):
    """lax.cond(pred, true_fn, false_fn, *operands); under vmap true_fn runs only if any pred is true."""
    true_conv, true_consts = _hoisted(true_fn, operands)
    false_conv, false_consts = _hoisted(false_fn, operands)

    @custom_batching.custom_vmap
    def cond(pred, true_consts, false_consts, operands):
        return jax.lax.cond(pred, lambda: true_conv(operands, true_consts),
                            lambda: false_conv(operands, false_consts))

    @cond.def_vmap
    def batched_cond(axis_size, in_batched, pred, true_consts, false_consts, operands):
        def broadcast(x, batched):
            return x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        args = jax.tree.map(broadcast, (pred, true_consts, false_consts, operands), tuple(in_batched))
        pred, true_consts, false_consts, operands = args
        run_true = jax.vmap(true_conv, axis_size=axis_size)
        run_false = jax.vmap(false_conv, axis_size=axis_size)

        def some_true():
            return _select(pred, run_true(operands, true_consts), run_false(operands, false_consts))

        out = jax.lax.cond(jnp.any(pred), some_true, lambda: run_false(operands, false_consts))
        return out, jax.tree.map(lambda _: True, out)

    return cond(pred, true_consts, false_consts, operands)
