"""Registers and spilled bytes per lane of Warp kernels on a CUDA architecture, without a GPU (docs/benchmarks.md,
session 26): each module is compiled ahead of time by Warp's NVRTC into a cubin, whose ``.nv.info`` section holds
every kernel's register count (EIATTR_REGCOUNT) and stack frame (EIATTR_FRAME_SIZE: spills and local arrays).

    python docs/scripts/kernel_registers.py [MODULE ...] [arch=90] [min=0]

MODULE: Python modules whose kernels to list (default: every module of ``lapreco_hil.frontend.warp``); kernels made
by a factory are listed where the module keeps one (e.g. ``lk._lk_track_slots``). ``min``: only kernels with at
least this many registers or with a stack frame. A block of B lanes with R registers each fits
floor(65536 / (R x B)) times on an SM of compute capability 9.0 (at most 2048 lanes).
"""
import importlib
import pkgutil
import struct
import sys
import tempfile

import warp as wp

_REGCOUNT, _FRAME_SIZE = 0x2F, 0x11


def cubin_resources(path: str) -> dict[str, tuple[int, int]]:
    """{kernel symbol: (registers, frame bytes)} of an ELF64 cubin."""
    b = open(path, "rb").read()
    shoff, = struct.unpack_from("<Q", b, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", b, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", b, shoff + i * shentsize) for i in range(shnum)]

    def name_at(table_offset: int, n: int) -> str:
        return b[table_offset + n:b.index(b"\0", table_offset + n)].decode()

    names = sections[shstrndx][4]
    symtab = next(s for s in sections if s[1] == 2)  # SHT_SYMTAB
    strtab = sections[symtab[6]][4]
    symbols = [name_at(strtab, struct.unpack_from("<I", b, symtab[4] + 24 * i)[0]) for i in range(symtab[5] // 24)]
    regs, frame = {}, {}
    for s in sections:
        if name_at(names, s[0]) != ".nv.info":
            continue
        p, end = s[4], s[4] + s[5]
        while p < end:
            fmt, attr = b[p], b[p + 1]
            if fmt == 0x04:  # EIFMT_SVAL: a u16 size, then the value
                size, = struct.unpack_from("<H", b, p + 2)
                if attr in (_REGCOUNT, _FRAME_SIZE) and size == 8:
                    symbol, value = struct.unpack_from("<II", b, p + 4)
                    (regs if attr == _REGCOUNT else frame)[symbols[symbol]] = value
                p += 4 + size
            elif fmt == 0x03:  # EIFMT_HVAL: a u16 value
                p += 4
            else:
                p += 2
    return {k: (v, frame.get(k, 0)) for k, v in regs.items()}


def main(argv: list[str]) -> None:
    opts = dict(a.split("=", 1) for a in argv if "=" in a)
    arch, least = int(opts.get("arch", "90")), int(opts.get("min", "0"))
    names = [a for a in argv if "=" not in a]
    if not names:
        import lapreco_hil.frontend.warp as package
        names = [f"{package.__name__}.{m.name}" for m in pkgutil.iter_modules(package.__path__)]
    wp.config.quiet = True
    out = tempfile.mkdtemp(prefix="kernel-registers-")
    for name in names:
        module = importlib.import_module(name)
        seen = set()
        for obj in vars(module).values():
            if not isinstance(obj, wp.Kernel) or id(obj.module) in seen:
                continue
            seen.add(id(obj.module))
            for path in wp.compile_aot_module(obj.module, arch=arch, module_dir=out, use_ptx=False):
                for kernel, (regs, frame) in sorted(cubin_resources(str(path)).items()):
                    if regs >= least or frame:
                        print(f"{name.rsplit('.', 1)[-1]:16s} {kernel.replace('_cuda_kernel_forward', ''):60s} "
                              f"{regs:4d} registers, {frame:5d} B frame")


if __name__ == "__main__":
    main(sys.argv[1:])
