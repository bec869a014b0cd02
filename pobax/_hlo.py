"""Memory traffic and kernel launches of a compiled program, counted from its optimised HLO, loops included.

    from pobax._hlo import traffic
    t = traffic(jax.jit(f).lower(*args).compile().as_text())
    t["bytes"], t["kernels"]        # per call of the program

XLA's own `cost_analysis()` counts a loop body once, whatever its trip count. This walks the optimised HLO from
the entry computation and multiplies each loop body by its trip count (`known_trip_count`, which XLA records on
the loops it can count; a loop without one is counted once and reported in `uncounted_loops`). Both branches of a
conditional are counted (an upper bound: one runs).

A kernel is every instruction of a non-fused computation that does work on the device: fusions, custom calls
(GEMMs, Triton), copies and the odd unfused op; parameters, tuples, bitcasts, constants and control flow are free.
Its bytes are the bytes of its operands and its result, with two refinements of what a kernel really touches:
a fusion operand read only through `dynamic-slice` / `slice` / `gather` counts the bytes of what those read, and
a `dynamic-update-slice` (fused or not) writes its update in place, so it counts the update, not the buffer.
Caches are ignored: this is the traffic to memory if nothing stayed in cache between kernels, an upper bound for
the small working sets of RL training (an H200's L2 holds 50 MB).
"""

import re

_BYTES = {"pred": 1, "s8": 1, "u8": 1, "s16": 2, "u16": 2, "f16": 2, "bf16": 2, "s32": 4, "u32": 4, "f32": 4,
          "s64": 8, "u64": 8, "f64": 8, "c64": 8, "c128": 16}
_FREE = {"parameter", "constant", "tuple", "get-tuple-element", "bitcast", "after-all", "partition-id",
         "replica-id", "iota", "opt-barrier", "add-dependency", "domain"}
_SLICING = {"dynamic-slice", "slice", "gather"}
_HEADER = re.compile(r"^(?:ENTRY )?%?([\w.\-]+) \(.*\) -> .* \{$")
_INSTR = re.compile(r"^\s*(?:ROOT )?%?([\w.\-]+) = (.*)$")
_ARRAY = re.compile(r"\b([a-z]+\d*)\[([\d,]*)\]")


def _shape_bytes(shape: str) -> int:
    total = 0
    for dtype, dims in _ARRAY.findall(shape):
        n = 1
        for d in filter(None, dims.split(",")):
            n *= int(d)
        total += n * _BYTES.get(dtype, 4)
    return total


def _split_type(rest: str) -> tuple[str, str]:
    """`TYPE opcode(...)...` → (TYPE, the rest); TYPE may be a parenthesised tuple."""
    if rest.startswith("("):
        depth = 0
        for i, ch in enumerate(rest):
            depth += ch == "("
            depth -= ch == ")"
            if depth == 0:
                return rest[: i + 1], rest[i + 1 :].lstrip()
    head, _, tail = rest.partition(" ")
    return head, tail


def _operands(call: str) -> tuple[str, list[str], str, str]:
    """`opcode(%a, %b), attrs` → (opcode, [a, b], attrs, the text between the parentheses)."""
    opcode, _, args = call.partition("(")
    depth, i = 1, 0
    while i < len(args) and depth:
        depth += args[i] == "("
        depth -= args[i] == ")"
        i += 1
    inner = args[: i - 1]
    return opcode.strip(), re.findall(r"%([\w.\-]+)", inner), args[i:], inner


def parse(hlo: str) -> dict[str, list[dict]]:
    """Computations of an HLO module's text: name → instructions (name, shape, opcode, operands, attrs, root,
    and a parameter's index); the entry computation is also under `__entry__`."""
    comps: dict[str, list[dict]] = {}
    current = None
    for line in hlo.splitlines():
        m = _HEADER.match(line)
        if m:
            current = comps.setdefault(m.group(1), [])
            if line.startswith("ENTRY"):
                comps["__entry__"] = current
            continue
        if line.startswith("}"):
            current = None
            continue
        m = _INSTR.match(line) if current is not None else None
        if m:
            shape, call = _split_type(m.group(2))
            opcode, ops, attrs, inner = _operands(call)
            current.append(dict(name=m.group(1), shape=shape, opcode=opcode, operands=ops, attrs=attrs,
                                root=line.lstrip().startswith("ROOT"),
                                index=int(inner) if opcode == "parameter" and inner.isdigit() else None))
    return comps


def _fusion_bytes(instr: dict, shapes: dict[str, str], comps: dict) -> int:
    """Bytes a fusion reads and writes (see the module docstring)."""
    m = re.search(r"calls=%([\w.\-]+)", instr["attrs"])
    body = comps.get(m.group(1), []) if m else []
    param = {i["index"]: i["name"] for i in body if i["opcode"] == "parameter"}
    users: dict[str, list[dict]] = {}
    for i in body:
        for o in i["operands"]:
            users.setdefault(o, []).append(i)
    by_name = {i["name"]: i for i in body}
    root = next((i for i in body if i["root"]), None)
    roots = [by_name[o] for o in root["operands"] if o in by_name] if root and root["opcode"] == "tuple" else \
        [root] if root else []
    in_place = {r["operands"][0] for r in roots if r["opcode"] == "dynamic-update-slice"}
    total = 0
    for k, operand in enumerate(instr["operands"]):
        pname = param.get(k)
        u = users.get(pname, [])
        if pname in in_place:
            continue  # the buffer updated in place: only the update is written (counted with the result)
        if u and all(x["opcode"] in _SLICING and x["operands"][0] == pname for x in u):
            total += sum(_shape_bytes(x["shape"]) for x in u)
        else:
            total += _shape_bytes(shapes.get(operand, ""))
    for r in roots:
        if r["opcode"] == "dynamic-update-slice":
            update = by_name.get(r["operands"][1])
            total += _shape_bytes(update["shape"]) if update else 0
        else:
            total += _shape_bytes(r["shape"])
    return total


def traffic(hlo: str) -> dict:
    """Bytes read and written by the kernels of one call of the program and kernels launched, each loop body
    counted per iteration (loop conditions are not counted); `loops`: (nesting depth, trip count) per loop."""
    comps = parse(hlo)
    out = dict(bytes=0.0, kernels=0.0, uncounted_loops=0, loops=[])

    def walk(name: str, mult: float, depth: int = 0) -> None:
        body = comps.get(name, [])
        shapes = {i["name"]: i["shape"] for i in body}
        for i in body:
            op, attrs = i["opcode"], i["attrs"]
            if op == "while":
                m = re.search(r'"known_trip_count":\{"n":"(\d+)"\}', attrs)
                n = int(m.group(1)) if m else 1
                out["uncounted_loops"] += m is None
                out["loops"].append((depth, n))
                walk(re.search(r"body=%([\w.\-]+)", attrs).group(1), mult * n, depth + 1)
                continue
            if op == "conditional":
                m = re.search(r"branch_computations=\{([^}]*)\}", attrs)
                branches = m.group(1) if m else " ".join(re.findall(r"(?:true|false)_computation=%[\w.\-]+", attrs))
                for b in re.findall(r"%([\w.\-]+)", branches):
                    walk(b, mult, depth + 1)
                continue
            if op == "call":
                walk(re.search(r"to_apply=%([\w.\-]+)", attrs).group(1), mult, depth + 1)
                continue
            if op in _FREE or op.endswith("-done") or op.endswith("-update"):
                continue
            if op == "fusion":
                b = _fusion_bytes(i, shapes, comps)
            elif op == "dynamic-update-slice":
                b = 2 * _shape_bytes(shapes.get(i["operands"][1], ""))
            else:
                b = _shape_bytes(i["shape"]) + sum(_shape_bytes(shapes.get(o, "")) for o in i["operands"])
            out["bytes"] += mult * b
            out["kernels"] += mult

    walk("__entry__", 1.0)
    return out

