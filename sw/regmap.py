"""Register addresses and field layouts, taken from the gateware's memory map.

Firmware never carries a register address or field offset of its own: it builds a
:class:`RegisterMap` from the memory map of the gateware it drives (the same object on the
Amaranth, cocotb and model backends), and names registers and fields.
"""

from dataclasses import dataclass

from amaranth.hdl import Shape


__all__ = ["Field", "Register", "RegisterMap", "windows", "to_markdown", "to_c_header"]


@dataclass(frozen=True)
class Field:
    """A field of a register: its bit offset and width."""
    name: str
    offset: int
    width: int

    @property
    def mask(self):
        return ((1 << self.width) - 1) << self.offset

    def extract(self, word):
        return (word >> self.offset) & ((1 << self.width) - 1)

    def insert(self, word, value):
        if not 0 <= value < 1 << self.width:
            raise ValueError(f"Field {self.name} is {self.width} bits wide; {value!r} does not fit")
        return (word & ~self.mask) | (value << self.offset)


@dataclass(frozen=True)
class Register:
    """A register: its name, word address and fields (by dotted path, e.g. ``cmd.timeout``)."""
    name: str
    address: int
    fields: dict
    access: str = ""
    doc: str = ""

    def field(self, name):
        try:
            return self.fields[name]
        except KeyError:
            raise KeyError(f"Register {self.name} has no field {name!r}; it has "
                           f"{', '.join(self.fields)}") from None

    def decode(self, word):
        """All fields of a word read from this register, by name."""
        return {name: f.extract(word) for name, f in self.fields.items()}

    def encode(self, **values):
        """A word with the given fields set (others zero); dotted names as ``a__b``."""
        word = 0
        for name, value in values.items():
            word = self.field(name.replace("__", ".")).insert(word, int(value))
        return word


def _layout_fields(prefix, shape, offset):
    """Fields of a struct-shaped field, flattened (``cmd.timeout``)."""
    from amaranth.lib import data
    try:
        layout = data.Layout.cast(shape)
    except TypeError:
        layout = None
    if isinstance(layout, data.StructLayout):
        fields = {}
        for name, member in layout:
            fields.update(_layout_fields(f"{prefix}.{name}", member.shape, offset + member.offset))
        return fields
    width = Shape.cast(shape).width
    return {prefix: Field(prefix, offset, width)}


class RegisterMap:
    """Registers of a CSR memory map, by name.

    Parameters
    ----------
    memory_map : amaranth_soc MemoryMap
        The gateware's map (e.g. ``SdioHost().bus.memory_map``).
    window : str or None
        Only the registers under this window of a decoder's map, named without it.
    base : int
        Word address of the map on the bus the firmware uses.
    """
    def __init__(self, memory_map, *, base=0, window=None):
        self._registers = {}
        for info in memory_map.all_resources():
            path = ["_".join(str(p) for p in part) for part in info.path]
            if window is not None:
                if path[0] != window:
                    continue
                path = path[1:]
            name = "_".join(path)
            fields, offset = {}, 0
            for path, action in info.resource.field.flatten():
                # The action's own data member keeps the field's declared shape (a struct
                # stays a struct); its port only has the cast width.
                members = action.signature.members
                data_member = next(members[n] for n in ("r_data", "w_data", "data")
                                   if n in members)
                shape = data_member.shape
                fields.update(_layout_fields(".".join(path), shape, offset))
                offset += Shape.cast(shape).width
            doc = " ".join((type(info.resource).__doc__ or "").split())
            access = info.resource.element.access.value
            self._registers[name] = Register(name, base + info.start, fields, access, doc)

    def __getitem__(self, name):
        try:
            return self._registers[name]
        except KeyError:
            raise KeyError(f"No register {name!r}; there are "
                           f"{', '.join(self._registers)}") from None

    def __iter__(self):
        return iter(self._registers.values())


def windows(memory_map, *, base=0):
    """The named windows of a memory map: ``{name: (first, end)}`` word addresses, ``end``
    excluded; a nameless window's own windows count as the map's."""
    found = {}
    for window, name, (start, end, _ratio) in memory_map.windows():
        if name is None:
            found.update(windows(window, base=base + start))
        else:
            found["_".join(str(p) for p in name)] = (base + start, base + end)
    return found


def to_markdown(regmap, *, title, memory_map=None):
    """The register map as a Markdown page: the windows of ``memory_map`` (when given), a
    table of registers, then their fields."""
    lines = [f"# {title}", "", "Generated from the gateware's memory map by "
             "`maglog hdl regmap`; word addresses, 32-bit registers.", ""]
    if memory_map is not None:
        lines += ["| window | first | last |", "|---|---:|---:|"]
        lines += [f"| `{name}` | {start:#04x} | {end - 1:#04x} |"
                  for name, (start, end) in windows(memory_map).items()]
        lines.append("")
    lines += ["| address | register | access | description |", "|---:|---|---|---|"]
    for reg in regmap:
        lines.append(f"| {reg.address:#04x} | `{reg.name}` | {reg.access} | {reg.doc} |")
    for reg in regmap:
        lines += ["", f"## `{reg.name}` ({reg.address:#04x})", "",
                  "| bits | field |", "|---|---|"]
        for field in reg.fields.values():
            top = field.offset + field.width - 1
            bits = f"{field.offset}" if field.width == 1 else f"{top}:{field.offset}"
            lines.append(f"| {bits} | `{field.name}` |")
    return "\n".join(lines) + "\n"


def to_c_header(regmap, *, prefix):
    """The register map as a C header: word addresses, field shifts and masks."""
    guard = f"{prefix.upper()}_REGS_H"
    lines = [f"/* Generated from the gateware's memory map by `maglog hdl regmap`. */",
             f"#ifndef {guard}", f"#define {guard}", ""]
    for reg in regmap:
        name = f"{prefix}_{reg.name}".upper()
        lines.append(f"#define {name}_ADDR {reg.address:#x}u")
        for field in reg.fields.values():
            fname = f"{name}_{field.name.replace('.', '_')}".upper()
            lines.append(f"#define {fname}_SHIFT {field.offset}u")
            lines.append(f"#define {fname}_MASK {field.mask:#x}u")
        lines.append("")
    lines.append(f"#endif /* {guard} */")
    return "\n".join(lines) + "\n"
