"""The deployed controller as an FMI 2.0 or 3.0 Co-Simulation FMU: the generated C step API in the FMI functions.

`fmu_sources(design, rate_hz, fmi="2"|"3")` gives every source file of the FMU ({name: text}): the generated step
pair of `files.generate(design, "c", prefix=<id>_, ...)` unchanged (one source: the FMU does not re-derive
anything), the wrapper `<id>_fmi2.c` / `<id>_fmi3.c` (templates/fmi2_cs.c, fmi3_cs.c) and the FMI headers
(templates/fmi2*.h, fmi3*.h, 2-Clause BSD, Modelica Association, their licence text kept in them);
`model_description` the modelDescription.xml; `build_fmu` compiles the binary for this platform (cached,
`core.ccompile`) and zips it all:

    <id>.fmu
      modelDescription.xml
      binaries/<platform>/<id>.so       (linux64 for FMI 2, x86_64-linux for FMI 3; the strict C99 flags, only the
                                         FMI functions exported)
      sources/<id>_fmi<V>.c, <base>.c, <base>.h, the FMI headers (and buildDescription.xml for FMI 3)

Variables (value references): inputs q[i], dq[i] (Real / Float64, causality input, variability discrete); outputs
tau[i], margin_e1[i], margin_e2[i] (1 - |e|/F), qd[i] and status (Integer / Int32: the last Pstep return code, 0
inside both funnels, 1 outside), all variability discrete, initial exact at the values before the first step
(Pinit's). The step takes no design numbers at run time (the gains, funnels, reference and rate are baked into the
generated C), so the FMU has no parameters. The GUID (FMI 3: instantiation token) is a hash of every source file and
of the model description, so two FMUs with the same GUID have the same behaviour. No clocks (see docs/fmu.md).
"""

from __future__ import annotations

import hashlib
import io
import re
import zipfile
from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

import numpy as np

__all__ = ["FMI_VERSIONS", "FmuSources", "model_identifier", "fmu_sources", "model_description", "build_fmu",
           "FMU_CFLAGS", "fmu_platform", "written_by_symfunnel"]

#: the FMI versions `codegen --lang fmu --fmi V` can produce
FMI_VERSIONS = ("2", "3")
#: flags the FMU's binary is built with: the generated code's strict flags, position-independent, and only the
#: FMI functions visible (CasADi's helpers and the step API stay inside the library)
FMU_CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-fPIC", "-shared",
              "-fvisibility=hidden", "-DCASADI_SYMBOL_EXPORT=")
_HEADERS = {"2": ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"),
            "3": ("fmi3Functions.h", "fmi3FunctionTypes.h", "fmi3PlatformTypes.h")}
#: the fixed time stamp of every zip entry (deterministic archive)
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class FmuSources:
    """Everything of one FMU but its binary: identifier, GUID, sources ({name: text}), modelDescription.xml."""

    identifier: str
    guid: str
    rate_hz: float
    n: int
    sources: dict[str, str]
    compile_files: tuple[str, ...]
    model_description: str
    fmi: str = "2"

    @property
    def platform(self) -> str:
        """The binaries/ folder of this platform for this FMI version."""
        return fmu_platform(self.fmi)


def model_identifier(name: str) -> str:
    """A C identifier made of the scenario's name (FMI's modelIdentifier names the library and the .fmu)."""
    ident = re.sub(r"[^A-Za-z0-9_]", "_", name) or "controller"
    if not re.match(r"[A-Za-z]", ident):
        ident = "m_" + ident
    return ident[:48]


def fmu_platform(fmi: str = "2") -> str:
    """The binaries folder for this machine: FMI 2 linux64, darwin64, win64 (32-bit variants); FMI 3 the
    architecture-os tuple (x86_64-linux, aarch64-darwin, x86_64-windows, ...)."""
    import platform
    import struct
    system = platform.system()
    if fmi == "3":
        arch = {"amd64": "x86_64", "x86_64": "x86_64", "arm64": "aarch64", "aarch64": "aarch64", "i386": "x86",
                "i686": "x86"}.get(platform.machine().lower(), platform.machine().lower())
        return f"{arch}-" + {"Linux": "linux", "Darwin": "darwin", "Windows": "windows"}.get(system, system.lower())
    bits = "64" if struct.calcsize("P") == 8 else "32"
    return {"Linux": "linux", "Darwin": "darwin", "Windows": "win"}.get(system, system.lower()) + bits


def _units(design) -> list[tuple[str, str, str]]:
    """Per joint (position, velocity, torque) units: rad, rad/s, N.m for a revolute joint; m, m/s, N prismatic."""
    types = list(getattr(design.scenario.model, "joint_types", []) or [])
    types += ["revolute"] * (design.n - len(types))
    return [("m", "m/s", "N") if t == "prismatic" else ("rad", "rad/s", "N.m") for t in types[:design.n]]


_UNIT_DEFS = {
    "rad": '<BaseUnit rad="1"/>', "rad/s": '<BaseUnit s="-1" rad="1"/>', "N.m": '<BaseUnit kg="1" m="2" s="-2"/>',
    "m": '<BaseUnit m="1"/>', "m/s": '<BaseUnit m="1" s="-1"/>', "N": '<BaseUnit kg="1" m="1" s="-2"/>',
    "1": "", "s": '<BaseUnit s="1"/>',
}


def _variables(design, tau_max) -> list[dict]:
    """The model variables in value-reference order (see the module doc)."""
    sc = design.scenario
    n = design.n
    units = _units(design)
    out = []
    for i in range(n):
        out.append({"name": f"q[{i + 1}]", "causality": "input", "type": "Real", "unit": units[i][0],
                    "start": float(sc.q0[i]), "description": f"measured position of joint {i + 1}"})
    for i in range(n):
        out.append({"name": f"dq[{i + 1}]", "causality": "input", "type": "Real", "unit": units[i][1],
                    "start": float(sc.dq0[i]), "description": f"measured velocity of joint {i + 1}"})
    sat = "" if tau_max is None else ", saturated at +-" + ", ".join(
        f"{v:g}" for v in np.broadcast_to(np.asarray(tau_max, dtype=float), (n,)))
    for i in range(n):
        out.append({"name": f"tau[{i + 1}]", "causality": "output", "type": "Real", "unit": units[i][2],
                    "start": 0.0, "description": f"torque of joint {i + 1} to hold until the next period{sat} "
                    "(0 before the first step)"})
    for f, rows in (("e1", "position"), ("e2", "velocity")):
        for i in range(n):
            out.append({"name": f"margin_{f}[{i + 1}]", "causality": "output", "type": "Real", "unit": "1",
                        "start": 1.0, "description": f"funnel margin 1 - |{f}|/F of joint {i + 1} ({rows} error; "
                        "< 0: outside that funnel), at the last step"})
    for i in range(n):
        out.append({"name": f"qd[{i + 1}]", "causality": "output", "type": "Real", "unit": units[i][0],
                    "start": 0.0, "description": f"reference position of joint {i + 1} at the last step"})
    out.append({"name": "status", "causality": "output", "type": "Integer", "unit": None, "start": 0,
                "description": "return code of the last controller step: 0 inside both funnels, 1 outside a "
                "funnel (tau still finite)"})
    for vr, v in enumerate(out):
        v["vr"] = vr
    return out


def model_description(design, *, identifier: str, guid: str, rate_hz: float, tau_max, source_files,
                      generator: str, fmi: str = "2") -> str:
    """modelDescription.xml of the FMI 2.0 or 3.0 Co-Simulation FMU (see the module doc)."""
    if fmi == "3":
        return _model_description_3(design, identifier=identifier, guid=guid, rate_hz=rate_hz, tau_max=tau_max,
                                    generator=generator)
    sc = design.scenario
    vs = _variables(design, tau_max)
    units = _unit_definitions(vs)
    lines = []
    for v in vs:
        typ = v["type"]
        start = repr(float(v["start"])) if typ == "Real" else str(int(v["start"]))
        unit = f' unit={quoteattr(v["unit"])}' if v["unit"] and typ == "Real" else ""
        initial = '' if v["causality"] == "input" else ' initial="exact"'
        lines.append(f'    <ScalarVariable name={quoteattr(v["name"])} valueReference="{v["vr"]}" '
                     f'causality="{v["causality"]}" variability="discrete"{initial}\n'
                     f'      description={quoteattr(v["description"])}>\n'
                     f'      <{typ}{unit} start="{start}"/>\n    </ScalarVariable>')
    outputs = "\n".join(f'      <Unknown index="{v["vr"] + 1}" dependencies=""/>' for v in vs
                        if v["causality"] == "output")
    files = "\n".join(f'      <File name={quoteattr(f)}/>' for f in source_files)
    desc = _description(sc, rate_hz, "fmi2DoStep")
    return f'''<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription
  fmiVersion="2.0"
  modelName={quoteattr(sc.name)}
  guid={quoteattr(guid)}
  description={quoteattr(desc)}
  generationTool={quoteattr(generator)}
  variableNamingConvention="structured"
  numberOfEventIndicators="0">
  <CoSimulation
    modelIdentifier={quoteattr(identifier)}
    needsExecutionTool="false"
    canHandleVariableCommunicationStepSize="true"
    canInterpolateInputs="false"
    maxOutputDerivativeOrder="0"
    canRunAsynchronuously="false"
    canBeInstantiatedOnlyOncePerProcess="false"
    canNotUseMemoryManagementFunctions="false"
    canGetAndSetFMUstate="true"
    canSerializeFMUstate="true"
    providesDirectionalDerivative="false">
    <SourceFiles>
{files}
    </SourceFiles>
  </CoSimulation>
  <UnitDefinitions>
{units}
  </UnitDefinitions>
  <LogCategories>
    <Category name="logStatusWarning" description={quoteattr("warnings: the state left a funnel")}/>
    <Category name="logStatusError" description={quoteattr("errors: a refused call, a failed step")}/>
  </LogCategories>
  <DefaultExperiment startTime="0.0" stopTime="{float(sc.simulation.t_final)!r}" stepSize="{1.0 / rate_hz!r}"/>
  <ModelVariables>
{chr(10).join(lines)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>
{outputs}
    </Outputs>
  </ModelStructure>
</fmiModelDescription>
'''


def _description(sc, rate_hz: float, do_step: str) -> str:
    return (f"Funnel controller of scenario '{sc.name}' ({sc.title}), deployed at {rate_hz:g} Hz: one {do_step} "
            f"period = 1/{rate_hz:g} s (a communication step must be a whole number of periods)")


def _unit_definitions(vs, extra=()) -> str:
    used = sorted({v["unit"] for v in vs if v["unit"]} | set(extra))
    return "\n".join(f'    <Unit name={quoteattr(u)}>{_UNIT_DEFS[u]}</Unit>' if _UNIT_DEFS[u]
                     else f'    <Unit name={quoteattr(u)}/>' for u in used)


def _model_description_3(design, *, identifier: str, guid: str, rate_hz: float, tau_max, generator: str) -> str:
    """modelDescription.xml of the FMI 3.0 Co-Simulation FMU: the FMI 2 variables as Float64 / Int32, no clocks, no
    event mode; the controller period is the fixedInternalStepSize and the DefaultExperiment's stepSize."""
    sc = design.scenario
    vs = _variables(design, tau_max)
    lines = []
    for v in vs:
        typ = "Float64" if v["type"] == "Real" else "Int32"
        start = repr(float(v["start"])) if typ == "Float64" else str(int(v["start"]))
        unit = f' unit={quoteattr(v["unit"])}' if v["unit"] and typ == "Float64" else ""
        initial = '' if v["causality"] == "input" else ' initial="exact"'
        lines.append(f'    <{typ} name={quoteattr(v["name"])} valueReference="{v["vr"]}" causality="{v["causality"]}" '
                     f'variability="discrete"{initial}{unit} start="{start}"\n'
                     f'      description={quoteattr(v["description"])}/>')
    lines.insert(0, f'    <Float64 name="time" valueReference="{len(vs)}" causality="independent" '
                    f'variability="continuous" unit="s"\n'
                    '      description="the FMU\'s time (the last communication point reached)"/>')
    outputs = "\n".join(f'    <Output valueReference="{v["vr"]}" dependencies=""/>' for v in vs
                        if v["causality"] == "output")
    h = 1.0 / rate_hz
    return f'''<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription
  fmiVersion="3.0"
  modelName={quoteattr(sc.name)}
  instantiationToken={quoteattr(guid)}
  description={quoteattr(_description(sc, rate_hz, "fmi3DoStep"))}
  generationTool={quoteattr(generator)}
  variableNamingConvention="structured">
  <CoSimulation
    modelIdentifier={quoteattr(identifier)}
    canGetAndSetFMUState="true"
    canSerializeFMUState="true"
    providesDirectionalDerivatives="false"
    providesAdjointDerivatives="false"
    canHandleVariableCommunicationStepSize="true"
    fixedInternalStepSize="{h!r}"
    maxOutputDerivativeOrder="0"
    hasEventMode="false"/>
  <UnitDefinitions>
{_unit_definitions(vs, ("s",))}
  </UnitDefinitions>
  <LogCategories>
    <Category name="logStatusWarning" description={quoteattr("warnings: the state left a funnel")}/>
    <Category name="logStatusError" description={quoteattr("errors: a refused call, a failed step")}/>
  </LogCategories>
  <DefaultExperiment startTime="0.0" stopTime="{float(sc.simulation.t_final)!r}" stepSize="{h!r}"/>
  <ModelVariables>
{chr(10).join(lines)}
  </ModelVariables>
  <ModelStructure>
{outputs}
  </ModelStructure>
</fmiModelDescription>
'''


def _build_description(identifier: str, compile_files) -> str:
    """sources/buildDescription.xml of an FMI 3.0 FMU: one C99 source file set, linked with the math library."""
    files = "\n".join(f'        <SourceFile name={quoteattr(f)}/>' for f in compile_files)
    return f'''<?xml version="1.0" encoding="UTF-8"?>
<fmiBuildDescription fmiVersion="3.0">
  <BuildConfiguration modelIdentifier={quoteattr(identifier)}>
    <SourceFileSet language="C99">
{files}
    </SourceFileSet>
    <Library name="m" external="true" description="the C math library (libm)"/>
  </BuildConfiguration>
</fmiBuildDescription>
'''


def _guid(parts: list[str]) -> str:
    h = hashlib.sha256("\0".join(parts).encode("utf-8")).hexdigest()
    return "{" + f"{h[:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:32]}" + "}"


def fmu_sources(design, rate_hz: float, tau_max=None, *, fmi: str = "2") -> FmuSources:
    """Every source of the FMU and its modelDescription.xml (no compiler run); deterministic."""
    from ..core.version import __version__
    from .c import template
    from .files import c_basename, generate
    from .step import step_settings
    if fmi not in FMI_VERSIONS:
        raise ValueError(f"FMI {fmi} is not supported (supported: {', '.join(FMI_VERSIONS)})")
    rate_hz, tau_max = step_settings(design, rate_hz, tau_max)
    sc = design.scenario
    ident = model_identifier(sc.name)
    prefix = ident + "_"
    base = c_basename(prefix)
    step = generate(design, "c", prefix=prefix, rate_hz=rate_hz, tau_max=tau_max)
    wrapper = f"{ident}_fmi{fmi}.c"
    compile_files = (wrapper, base + ".c")
    generator = f"symfunnel {__version__}"
    md_free = model_description(design, identifier=ident, guid="", rate_hz=rate_hz, tau_max=tau_max,
                                source_files=compile_files, generator=generator, fmi=fmi)
    wrapper_text = template(f"fmi{fmi}_cs.c")
    guid = _guid([md_free, step[base + ".c"], step[base + ".h"], wrapper_text])
    subs = {"@SCENARIO@": sc.name, "@BASENAME@": base, "@P@": prefix, "@ID@": ident, "@N@": str(design.n),
            "@GUID@": guid, "@RATE@": repr(float(rate_hz)),
            "@Q0@": ", ".join(repr(float(v)) for v in sc.q0), "@DQ0@": ", ".join(repr(float(v)) for v in sc.dq0)}
    for k, v in subs.items():
        wrapper_text = wrapper_text.replace(k, v)
    sources = {wrapper: wrapper_text, base + ".c": step[base + ".c"], base + ".h": step[base + ".h"],
               **{h: template(h) for h in _HEADERS[fmi]}}
    if fmi == "3":
        sources["buildDescription.xml"] = _build_description(ident, compile_files)
    md = model_description(design, identifier=ident, guid=guid, rate_hz=rate_hz, tau_max=tau_max,
                           source_files=compile_files, generator=generator, fmi=fmi)
    return FmuSources(ident, guid, float(rate_hz), design.n, sources, compile_files, md, fmi)


def build_binary(src: FmuSources, on_build=None):
    """Compile the FMU's shared library for this platform (cached by its sources): `core.ccompile.Built`."""
    from ..core.ccompile import compile_cached
    return compile_cached(src.sources, list(src.compile_files), src.identifier + ".so", FMU_CFLAGS,
                          on_build=on_build)


def build_fmu(src: FmuSources, on_build=None) -> bytes:
    """The .fmu archive (zip) as bytes: modelDescription.xml, the binary for this platform, the sources."""
    binary = build_binary(src, on_build=on_build).path.read_bytes()
    entries = [("modelDescription.xml", src.model_description.encode("utf-8")),
               (f"binaries/{src.platform}/{src.identifier}.so", binary)]
    entries += [(f"sources/{name}", text.encode("utf-8")) for name, text in src.sources.items()]
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries:
            info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = (0o755 if name.endswith(".so") else 0o644) << 16
            zf.writestr(info, data)
    return buf.getvalue()


def written_by_symfunnel(path) -> bool:
    """True when `path` is an FMU whose modelDescription.xml names symfunnel as its generation tool."""
    try:
        with zipfile.ZipFile(path) as zf:
            md = zf.read("modelDescription.xml").decode("utf-8", "replace")
    except (OSError, zipfile.BadZipFile, KeyError, ValueError):
        return False
    m = re.search(r'generationTool="([^"]*)"', md)
    return bool(m and m.group(1).startswith("symfunnel"))

