"""How estim runs on JAX: float64 always, compiled programs kept on disk, compile options.

Importing estim switches JAX's 64-bit mode on (``jax_enable_x64``), because event times
and their sensitivities lose most of their digits in float32. If 64-bit mode is switched
off afterwards, every entry point raises instead of returning float32 results.

If JAX has not started its backend yet, importing estim also sets two things JAX reads
when it starts it: XLA's small-loop threshold (``XLA_FLAGS``, below), and synchronous
dispatch on the CPU (``jax_cpu_enable_async_dispatch = False``: programs run on the
calling thread; ``ESTIM_ASYNC_DISPATCH=1`` keeps JAX's default). Both change how programs
run, not what they compute.
"""

import contextlib
import functools
import os
import threading
import time
from collections.abc import Callable

import equinox as eqx
import jax

jax.config.update("jax_enable_x64", True)

# XLA:CPU runs a program as a sequence of kernels, each at a fixed cost, and an event
# loop's body is a few hundred small kernels per iteration. A while loop (a lax.while_loop
# or lax.scan) that touches fewer bytes per trip than this threshold, and calls no library
# (dot, scatter, custom call), is instead compiled into one kernel. XLA's default
# threshold, 1 KiB, leaves estim's loops out; at 300 kB the closed-form `simulate` (one
# loop over balls, estim.forward._simulate) is one kernel for any number of balls, and so is the
# ODE path's step loop for a single ball. Measured with `estim bench speed` (2-core
# reference machine, jax 0.10.2) when the loops first became kernels: forward, 3 balls
# 744 -> 357 us; gradient (jacfwd) of the golf ball 561 -> 171 us; figures since then in
# docs/pages/speed.md. 600 kB since the ODE path's loop over balls (each ball's step loop
# and replay, with the argument checks of a call inside a user's jit) outgrew 300 kB: a
# table-tennis shot in air took 165-200 us instead of 89 us; the closed-form figures are
# the same at either threshold (forward 27.5 us, jacfwd 25.4 us, 1.17e6 balls/s).
SMALL_LOOP_BYTES = 600_000
_SMALL_LOOP_OPTION = "xla_cpu_small_while_loop_byte_threshold"


def _set_small_loop_threshold() -> bool:
    """Raise XLA:CPU's small-loop threshold through ``XLA_FLAGS`` (XLA reads it once, when
    JAX starts its backend, so only before that). Leaves a user's own
    ``xla_backend_extra_options`` alone. Returns whether the threshold is estim's."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_extra_options" in flags:
        return f"{_SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}" in flags
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return False
    option = f"--xla_backend_extra_options={_SMALL_LOOP_OPTION}={SMALL_LOOP_BYTES}"
    os.environ["XLA_FLAGS"] = f"{flags} {option}".strip()
    return True


SMALL_LOOPS_AS_KERNELS = _set_small_loop_threshold()

# DISPATCH: by default JAX's CPU client runs a compiled program on a thread of its own
# pool, and the calling thread sleeps until it is done: a hand-over between threads at
# every call, which on the 2-core reference machine cost up to 40 us more than the whole
# gradient of the golf ball (38 us when run on the calling thread; docs/pages/speed.md).
# estim's programs are microseconds long and their callers wait for the result, so estim
# asks JAX to run programs on the calling thread (``jax_cpu_enable_async_dispatch``). JAX
# reads this once, when it starts its backend, so only before that; ``ESTIM_ASYNC_DISPATCH=1``
# leaves JAX's default, as does setting the option back after importing estim, before the
# first computation.
_ASYNC_OPTION = "jax_cpu_enable_async_dispatch"


def _set_sync_dispatch() -> bool:
    """Ask JAX's CPU client to run programs on the calling thread, if its backend has not
    started and ``ESTIM_ASYNC_DISPATCH`` is not ``1``. Returns whether estim set it."""
    if os.environ.get("ESTIM_ASYNC_DISPATCH") == "1":
        return False
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        return False
    try:
        jax.config.update(_ASYNC_OPTION, False)
    except AttributeError:  # a JAX without the option: nothing to set
        return False
    return True


SYNC_DISPATCH = _set_sync_dispatch()


def dispatch_is_sync() -> bool:
    """Whether JAX's CPU client runs programs on the calling thread (the option as JAX
    read it when its backend started, or will read it)."""
    return not bool(getattr(jax.config, "values", {}).get(_ASYNC_OPTION, True))

# TRACING: JAX traces a Python function at every call, and a first call of `simulate`
# spends about a second tracing. The closed forms that a program calls dozens of times
# (geometric sums, powers, entering times, a flight's start) are wrapped in `jax.jit`, so
# that each is traced once per signature (when introduced: `simulate` on the seed scene
# traced in 0.7 s instead of 1.0 s, its `jacfwd` in 1.5 s instead of 2.7 s). The compiled
# code is the same (XLA inlines the calls).


def keep_loop(x):
    """``x``, the result of a loop, with the loop marked for XLA to keep even when it runs
    once (XLA otherwise replaces a loop of one trip by its body: kernels of their own).
    A JAX without the value form ``set_xla_metadata(x, ...)`` leaves the loop unmarked
    (it runs as before: the same results, more kernels)."""
    try:
        from jax.experimental.xla_metadata import set_xla_metadata

        return set_xla_metadata(x, **{"skip-simplify-while-loops_trip-count-one": "true"})
    except (ImportError, TypeError):
        return x


def require_x64() -> None:
    if not jax.config.jax_enable_x64:
        raise RuntimeError(
            "estim needs JAX's 64-bit mode, which was switched off after importing estim; "
            "run jax.config.update('jax_enable_x64', True)"
        )


def enable_compilation_cache(path: str | None = None) -> str | None:
    """Keep compiled programs on disk, so a new process skips most of JAX's compile time.

    Uses JAX's persistent compilation cache at ``path`` (default ``$ESTIM_CACHE_DIR`` or
    ``~/.cache/estim/jax``). Leaves an existing JAX cache setting alone; ``ESTIM_NO_CACHE=1``
    turns it off. The ``estim`` command calls this; library users may. Returns the directory
    used, or None.
    """
    import os

    if os.environ.get("ESTIM_NO_CACHE") == "1":
        return None
    current = jax.config.jax_compilation_cache_dir
    if current:
        return current
    path = path or os.environ.get("ESTIM_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "estim", "jax"
    )
    try:
        os.makedirs(path, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path


# Compile options for estim's programs, on XLA:CPU. Event loops are thousands of small
# fusions, and XLA's MLIR fusion emitters spend most of the compile time on them: with the
# classic emitters `simulate` on the seed scene compiles in 3.0 s instead of 4.6 s and runs
# as fast (measured on the 2-core reference machine, jax 0.10.2).
FAST_COMPILE = (("xla_cpu_use_fusion_emitters", False),)
# A fit compiles one program per process and runs it a few times (window, all data,
# restarts). In a vacuum (the closed form) XLA's default optimisation: at level 0 the
# program of the bundled staircase compiled 0.3 s faster and ran 5.5 times slower (60 balls,
# 458 against 83 us per ball and iteration). On the ODE path the compile is the larger
# cost: the table-tennis shot's fit program (estim bench fit's TABLE_SHOT) compiled and ran
# in 6.8 s and 85 ms at level 0, 9.6 s and 17 ms at level 1, 10.3 s and 30 ms at level 2,
# 13.3 s and 28 ms at the default (2-core reference machine, jax 0.10.2). A fit's program
# is compiled at level 0 first (most processes fit once) and at level 1 once the same
# program has run FIT_ODE_TIER_UP times in the process (many shots, many clips;
# ``estim.fitting._fit.fit_program``). The count is the ski-rental one: the quick program
# runs until its calls have cost about what the second compile costs. The one-camera
# shot's program (`estim bench fit`, five calls per fit) compiled at level 1 in about
# 15 s and ran in 0.22 s per call at level 0 (2-core development machine, session 49:
# fits of 11.8 s then 1.5 s each at level 0, 15.5 s then 0.5 s at level 1): 15 / 0.22 =
# 68 calls; the table-tennis shot's above, 9.6 s / 85 ms = 113. (After 8 calls, the
# second shot of a process took 18.7 s instead of 1.5 s.) A process that knows it will
# fit many shots can enter ``optimised_programs`` and skip the quick program.
FIT_COMPILE = FAST_COMPILE
FIT_ODE_COMPILE = FAST_COMPILE + (("xla_backend_optimization_level", 0),)
FIT_ODE_OPTIMISED = FAST_COMPILE + (("xla_backend_optimization_level", 1),)
FIT_ODE_TIER_UP = 64
# The closed-form `simulate`, one loop kernel (SMALL_LOOP_BYTES), with LLVM's level-1
# optimisation. Chosen when its planning loop alone was a kernel (3 balls compiled in 4.4 s
# instead of 5.2 s, ran as fast); as one loop over balls, levels 1 and 3 are within noise
# of each other (one CPU, two runs each: compile 2.4-2.8 s, 3 balls 145-157 us, 10,000
# balls 151-174 ms).
CLOSED_FORM_COMPILE = FAST_COMPILE + (("xla_backend_optimization_level", 1),)
# The ODE path (estim.forward._ode), one step loop per ball: XLA's defaults. Its steps are
# arithmetic on a few vectors, which the fusion emitters compile into faster code: 3 balls
# in still air ran in 0.63 ms with them, 1.36 ms without, and compiled in the same 4.0 s
# (2-core reference machine, jax 0.10.2); at optimisation level 0, 2.2 ms in 3.0 s. At top
# level (``estim.simulate`` called directly) a program starts with the fit's quick options
# and moves to these once it has run as long as its first call took (``jit``'s
# ``optimised``): the seed's 3 balls in still air, every part kept, compiled in 2.4 s
# instead of 4.4 s and ran in 6.9 ms instead of 1.2 ms (2-core development machine, AMD
# EPYC, session 36), so a single call, the common case there, takes half the time.
ODE_COMPILE = FIT_ODE_COMPILE
ODE_OPTIMISED = ()


@functools.cache
def compile_options(options: tuple[tuple[str, object], ...]) -> dict:
    """The options this XLA build accepts (one trivial compile each, once per process): an
    option a newer or older jaxlib does not know is left out, never an error."""
    accepted = {}
    for name, value in options:
        try:
            jax.jit(lambda x: x, compiler_options={name: value}).lower(0.0).compile()
        except Exception:  # XLA: "No such compile option"
            continue
        accepted[name] = value
    return accepted


_HELD = threading.local()


@contextlib.contextmanager
def same_programs():
    """Top-level calls inside run on the programs their signatures have on entry: the
    ski-rental rule's move to the optimised program (timed, so it falls where the
    machine's load puts it) waits until the block ends. Runs compared with each other
    (a ball with and without an effect) then round alike."""
    held, _HELD.on = getattr(_HELD, "on", False), True
    try:
        yield
    finally:
        _HELD.on = held


@contextlib.contextmanager
def optimised_programs():
    """Fits (and other tiered programs) called inside compile their optimised program
    from their first call, and keep it after the block: for a process that knows it will
    fit many shots, where the quick program and the count that tiers up would only cost
    time. The one-camera shot of ``estim bench fit`` (2-core development machine): 15.5 s,
    then 0.5 s per fit, against 11.8 s, then 1.5 s for its first 12 fits without it.

    ```python
    with estim.optimised_programs():
        fits = [estim.fit_image(scene, tracks) for tracks in shots]
    ```
    """
    on, _HELD.optimised = getattr(_HELD, "optimised", False), True
    try:
        yield
    finally:
        _HELD.optimised = on


def top_level() -> bool:
    """Whether no JAX transformation is tracing (JAX takes compile options only from a
    top-level jit: inside a user's jit the outer program is what gets compiled)."""
    clean = getattr(jax._src.core, "trace_state_clean", None)
    return bool(clean()) if clean is not None else False


def signature(tree) -> tuple:
    """What a compiled program depends on in ``tree`` (arguments): its structure, the shape
    and dtype of every array (or ``jax.ShapeDtypeStruct``) and the value of every other
    leaf (static, as ``filter_jit`` treats it)."""
    leaves, structure = jax.tree.flatten(tree)
    return structure, tuple((x.shape, x.dtype) if eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct) else x
                            for x in leaves)


def jit(fun: Callable | None = None, *, options: tuple[tuple[str, object], ...] = FAST_COMPILE,
        static_argnames: tuple[str, ...] | None = None,
        optimised: tuple[tuple[str, object], ...] | None = None, tier_up: int | None = None):
    """``equinox.filter_jit``, with the XLA compile ``options`` when called at top level.

    With ``static_argnames``, ``jax.jit`` instead: every other argument must then be a
    pytree of arrays. It splits the arguments in C++, where ``filter_jit`` partitions
    them in Python at every call (the direct call of ``simulate``: 0.15 ms of filter_jit
    for 0.07 ms of program).

    With ``optimised``, ``options`` are the quick ones (compiled fast, run slowly), and a
    program (one ``signature`` of the arguments) is compiled again with ``optimised``
    after ``tier_up`` calls, or by default once its quick program has run, after its
    first call, as long as that first call took (compile included): the ski-rental rule,
    which never spends more than about twice what knowing the number of calls in advance
    would. Under that rule top-level calls wait for their results (to time them) until
    their program moves on.

    The wrapper's ``ahead(*args, **kwargs)`` (with ``static_argnames`` and the ski-rental
    rule) lowers the quick program of a signature not seen yet, whose arguments may be
    ``jax.ShapeDtypeStruct``, and returns ``(out_info, compile)``, else None: ``compile()``
    compiles it, on any thread (XLA releases the GIL, so programs compile side by side),
    and the top-level call finds it compiled; the time spent counts as that call's."""
    if fun is None:
        return functools.partial(jit, options=options, static_argnames=static_argnames, optimised=optimised,
                                 tier_up=tier_up)

    def wrap(**compiler):
        if static_argnames is None:
            return eqx.filter_jit(fun, **compiler)
        return jax.jit(fun, static_argnames=static_argnames, **compiler)

    nested = wrap()
    top = fast = None
    spent = {}  # signature -> seconds of its quick program's calls (the first, the rest), or calls; None once optimised

    def quick():
        nonlocal top
        if top is None:
            top = wrap(compiler_options=compile_options(options))
        return top

    @functools.wraps(fun)
    def call(*args, **kwargs):
        nonlocal fast
        if not top_level():
            return nested(*args, **kwargs)
        if optimised is None:
            return quick()(*args, **kwargs)
        key = signature((args, kwargs))
        try:
            clock = spent.setdefault(key, [0.0, 0.0])
        except TypeError:  # (a static leaf that cannot be hashed: filter_jit will say so)
            return quick()(*args, **kwargs)
        if clock is None or getattr(_HELD, "optimised", False):
            spent[key] = None
            if fast is None:
                fast = wrap(compiler_options=compile_options(optimised))
            return fast(*args, **kwargs)
        if getattr(_HELD, "on", False):  # (same_programs: neither counted nor timed)
            return quick()(*args, **kwargs)
        if tier_up is not None:  # (counted: clock[0] is the number of calls)
            clock[0] += 1
            if clock[0] >= tier_up:
                spent[key] = None
            return quick()(*args, **kwargs)
        start = time.perf_counter()
        out = jax.block_until_ready(quick()(*args, **kwargs))
        clock[bool(clock[0])] += time.perf_counter() - start
        if clock[1] >= clock[0]:
            spent[key] = None
        return out

    def ahead(*args, **kwargs):
        if static_argnames is None or optimised is None or tier_up is not None:
            raise TypeError("ahead needs static_argnames and the ski-rental rule (optimised, no tier_up)")
        key = signature((args, kwargs))
        if key in spent:
            return None
        start = time.perf_counter()
        lowered = quick().trace(*args, **kwargs).lower()
        clock = spent[key] = [time.perf_counter() - start, 0.0]

        def compile_():
            begin = time.perf_counter()
            lowered.compile()
            clock[0] += time.perf_counter() - begin

        return lowered.out_info, compile_

    call.ahead = ahead
    return call
