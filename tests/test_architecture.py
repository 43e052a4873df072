"""ARCHITECTURE.md against the code: its station port table names the ports the stations
really have, the ports it gives DexRepSystem, PolicySystem and the controller-less diagram are
theirs, and every repository file it cites exists."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TEXT = (REPO / "ARCHITECTURE.md").read_text()


def _port_table() -> dict[str, str]:
    """port name -> direction cell of the table under the station section."""
    rows = re.findall(r"^\| `([a-z_]+)` \| ([a-z ,]+) \|", TEXT, flags=re.MULTILINE)
    assert rows, "ARCHITECTURE.md holds no port table"
    return dict(rows)


def _ports(diagram) -> tuple[list[str], list[str]]:
    return ([diagram.get_input_port(i).get_name() for i in range(diagram.num_input_ports())],
            [diagram.get_output_port(i).get_name() for i in range(diagram.num_output_ports())])


def test_the_port_table_names_the_sim_stations_ports():
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import PORTS, make_station

    table = _port_table()
    inputs, outputs = _ports(make_station(load_scenario("sim")).diagram)
    assert sorted(n for n, d in table.items() if d.startswith("input")) == sorted(inputs)
    assert sorted(n for n, d in table.items() if d.startswith("output")) == sorted(outputs)
    # the ports every mode shares (hil and real build theirs from PORTS) are the table's
    # rows that are not marked for one mode
    common = sorted(n for n, d in table.items() if "only" not in d)
    assert common == sorted((*PORTS["inputs"], *PORTS["outputs"]))


def _system_ports(name: str) -> tuple[set[str], set[str]]:
    """(input, output) port names the text gives `name` ("`Name` ...: input(s) ..., output `x`")."""
    match = re.search(rf"`{name}`[^:]*:\s+inputs?\s+(.*?),\s+output\s+`(\w+)`", TEXT, flags=re.DOTALL)
    assert match, f"ARCHITECTURE.md names no ports of {name}"
    return set(re.findall(r"`(\w+)`", match.group(1))), {match.group(2)}


def test_the_systems_ports_are_those_the_architecture_names():
    import torch

    from dexdrake.learn.policy import DexRepNetPolicy, PolicyConfig
    from dexdrake.systems.diagram import build_diagram
    from dexdrake.systems.policy_system import PolicySystem
    from dexdrake.systems.scenario import load_scenario
    from dexdrake.systems.station import make_station

    torch.manual_seed(0)
    built = build_diagram(make_station(load_scenario("sim")))  # no controller: training's diagram
    # "With no controller (training), `command` is the diagram's input and `features` an output"
    inputs, outputs = _ports(built.diagram)
    assert inputs == ["command"] and {"features", "hand_state", "object_pose"} <= set(outputs)
    dexrep_inputs, dexrep_outputs = _ports(built.dexrep)
    assert _system_ports("DexRepSystem") == (set(dexrep_inputs), set(dexrep_outputs))
    policy = DexRepNetPolicy(PolicyConfig.from_blocks({"hand": 4}, 2))
    policy_inputs, policy_outputs = _ports(PolicySystem(policy, 0.02))
    assert _system_ports("PolicySystem") == (set(policy_inputs), set(policy_outputs))


def test_every_file_the_architecture_cites_exists():
    cited = set(re.findall(r"\b((?:dexdrake|systems|hardware|scripts|tests|configs)/[\w/]+\.(?:py|yaml|md))", TEXT))
    assert cited, "no file citations found"
    missing = sorted(p for p in cited if not (REPO / p).is_file()
                     and not (REPO / "dexdrake" / p).is_file())
    assert not missing, f"ARCHITECTURE.md cites files that do not exist: {missing}"
