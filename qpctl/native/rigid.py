"""The tick's rigid-body pass on the native library (``rigid_pass.cpp``): a handle owning a copy of the
controller's model and its own ``pinocchio::Data``, and numpy views of that Data's arrays, laid out as
:func:`qpctl.tick.bind_pinocchio`'s views of a ``pin.Data`` are. The compiled tick calls the pass
through its address (:mod:`qpctl.kernels.pin_native`); :func:`qpctl.tick.rigid_pass` stays the path
where the library is unavailable and for robots whose configuration is not a vector space.
"""

from __future__ import annotations

import ctypes
import weakref

import numpy as np
import pinocchio as pin

import qpctl.native


def float_view(address: int, shape: tuple[int, ...]) -> np.ndarray:
    """A float64 numpy view of memory owned by someone else (kept alive by its owner: the handle, or
    the workspace's ``pin.Data``)."""
    size = int(np.prod(shape))
    return np.ctypeslib.as_array((ctypes.c_double * size).from_address(address)).reshape(shape)


class NativeRigid:
    """crba (world convention) and nonLinearEffects of ``model`` on the native library.

    ``address`` and ``handle`` are what the compiled tick calls; :attr:`views` are the arrays the
    tick reads (``oMi``, ``acc_gf``, ``Jt``, ``Mt``, ``nle``, as :func:`qpctl.tick.bind_pinocchio`'s).
    Checked on construction against the bindings' ``crba`` and ``nonLinearEffects`` on random states:
    the same numbers bit for bit (the same libpinocchio functions), or :class:`RuntimeError`.
    Use :meth:`create`, which returns None where the library is unavailable.
    """

    def __init__(self, lib: ctypes.CDLL, model: pin.Model) -> None:
        text = model.saveToString().encode()
        handle = lib.qpr_new(text, len(text))
        if not handle:
            raise RuntimeError(f"the native rigid-body pass refused the model: {lib.qpr_error().decode()}")
        self.handle = int(handle)
        self._free = weakref.finalize(self, lib.qpr_free, handle)
        self.lib, self.model = lib, model
        self.address = ctypes.cast(lib.qpr_pass, ctypes.c_void_p).value or 0
        addr = (ctypes.c_uint64 * 6)()
        lib.qpr_addresses(handle, addr)
        nj, n = model.njoints, model.nv
        if nj > 1 and addr[5] != 12 * 8:
            raise RuntimeError(f"pinocchio::Data's placements are {addr[5]} bytes apart, not 96, in this build")
        self.views = {"oMi": float_view(addr[0], (nj, 12)), "acc_gf": float_view(addr[1], (nj, 6)), "Jt": float_view(addr[2], (n, 6)),
                      "Mt": float_view(addr[3], (n, n)), "nle": float_view(addr[4], (n,))}
        self._check()

    @classmethod
    def create(cls, model: pin.Model) -> NativeRigid | None:
        """The pass for ``model``, or None where the native library cannot be built or loaded
        (:func:`qpctl.native.why_unavailable`) or the configuration is not a vector space."""
        if model.nq != model.nv:
            return None
        lib = qpctl.native.library()
        return None if lib is None else cls(lib, model)

    def run(self, q: np.ndarray, v: np.ndarray) -> None:
        """One pass at (q, v) (float64 vectors of nq and nv), gravity from the model's; through ctypes
        (the tests' and the checks' call; the tick calls it from the kernel)."""
        q = np.ascontiguousarray(q, dtype=float)
        v = np.ascontiguousarray(v, dtype=float)
        if q.shape != (self.model.nq,) or v.shape != (self.model.nv,):
            raise ValueError(f"q and v must have shapes ({self.model.nq},) and ({self.model.nv},)")
        g = np.ascontiguousarray(self.model.gravity.linear, dtype=float)
        if self.lib.qpr_pass(self.handle, q.ctypes.data, v.ctypes.data, g.ctypes.data):
            raise RuntimeError(f"Pinocchio: {self.lib.qpr_error().decode()}")

    def error(self) -> str:
        """The library's message for the last pass that failed."""
        return str(self.lib.qpr_error().decode())

    def _check(self) -> None:
        """The views after :meth:`run` against the bindings' crba and nonLinearEffects, exactly."""
        model, data = self.model, self.model.createData()
        rng = np.random.default_rng(0)
        for _ in range(3):
            q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq)) if model.nq else np.zeros(0)
            v = rng.uniform(-1, 1, model.nv)
            self.run(q, v)
            pin.crba(model, data, q, pin.Convention.WORLD)
            pin.nonLinearEffects(model, data, q, v)
            # M: its upper triangle, what crba computes (the bindings copy it into the lower one too)
            ok = np.array_equal(self.views["Jt"], data.J.T) and np.array_equal(np.tril(self.views["Mt"]), np.tril(data.M.T)) \
                and np.array_equal(self.views["nle"], data.nle)
            for j in range(model.njoints):
                H = data.oMi[j]
                ok = ok and np.array_equal(self.views["oMi"][j, :9].reshape(3, 3).T, H.rotation) \
                    and np.array_equal(self.views["oMi"][j, 9:], H.translation) \
                    and np.array_equal(self.views["acc_gf"][j], data.a_gf[j].vector)
            if not ok:
                raise RuntimeError("the native rigid-body pass disagrees with Pinocchio's bindings in this build")
