"""ARCHITECTURE.md against the code: its station port table names the ports the stations
really have, and every repository file it cites exists."""

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


def test_every_file_the_architecture_cites_exists():
    cited = set(re.findall(r"\b((?:dexdrake|systems|hardware|scripts|tests|configs)/[\w/]+\.(?:py|yaml|md))", TEXT))
    assert cited, "no file citations found"
    missing = sorted(p for p in cited if not (REPO / p).is_file()
                     and not (REPO / "dexdrake" / p).is_file())
    assert not missing, f"ARCHITECTURE.md cites files that do not exist: {missing}"
