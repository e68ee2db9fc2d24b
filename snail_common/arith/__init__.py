"""Arithmetic circuits on CircuitBuilder words: integers and IEEE-754 binary32.

Every function takes a CircuitBuilder and word arrays of wire ids (last axis = bits, LSB
first) of any broadcastable leading shape, and returns new words; no function loops over
lanes. Modules: ``words`` (bit plumbing), ``integer`` (adders, comparators), ``prefix``
(log-depth adder), ``shift`` (barrel shifters, leading zeros), ``multiply`` (integer
products), ``fbits`` (float fields, rounding), ``fadd``/``fmul``/``fdiv``/``fsqrt``/``fcmp``/
``fconvert``/``fconst`` (float32 ops), ``mirror`` (numpy reference of the float ops).
"""
