"""program_digest: equal programs give equal digests however JAX shares their sub-jaxprs; changes show."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tests.program_digest import program_digest


def _scaled(offset):
    return jax.jit(lambda x: jnp.tanh(x) * 2.0 + offset)


def _twice(first, second):
    return lambda x: second(first(x))


def test_a_shared_and_an_unshared_copy_of_a_sub_program_digest_alike_but_print_differently():
    x = jnp.ones(3)
    one = _scaled(1.0)
    shared, unshared = _twice(one, one), _twice(one, _scaled(1.0))
    assert str(jax.make_jaxpr(shared)(x)) != str(jax.make_jaxpr(unshared)(x))  # the printer's sharing
    assert program_digest(shared, x) == program_digest(unshared, x)


def test_a_changed_literal_shape_or_primitive_changes_the_digest():
    x = jnp.ones(3)
    base = program_digest(_twice(_scaled(1.0), _scaled(1.0)), x)
    assert program_digest(_twice(_scaled(1.0), _scaled(1.5)), x) != base
    assert program_digest(_twice(_scaled(1.0), _scaled(1.0)), jnp.ones(4)) != base
    assert program_digest(_twice(_scaled(1.0), jnp.sin), x) != base
