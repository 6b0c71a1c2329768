"""The stability report's table image: rows = cases, columns = methods, a cell per result."""

from __future__ import annotations

from collections.abc import Mapping
import os
from typing import Any

from feeder_sim.reports.stability.cases import SCENES

_COLOURS = {'PASS': '#c8e6c9', 'FAIL': '#ef9a9a', 'FAILS BY DESIGN': '#ffe0b2'}


def _cell_text(cell: Mapping[str, Any], case_key: str) -> str:
    lines = [cell['status']]
    case = SCENES.get(case_key)
    key = case.criteria[0].metric if case is not None and case.criteria else 'energy_gain'
    measured = cell.get('measured', {})
    if key and measured.get(key) is not None:
        lines.append(f'{key} {measured[key]:.2g}')
    pen, fb = cell.get('max_penetration_m'), cell.get('fallbacks')
    lines.append(('' if pen is None else f'pen {pen:.1e} m, ') + f'{cell["wall_s"]:.1f} s'
                 + ('' if not fb else f', fallbacks {fb}'))
    if not cell['passed'] and cell.get('failures'):
        lines.append(cell['failures'][0][:44])
    return '\n'.join(lines)


def write_table_png(report: Mapping[str, Any], path: str | os.PathLike) -> None:
    """The report as a coloured table image: one row per case, one column per method."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    methods = report['methods']
    keys = list(report['cases'])
    by = {(c['case'], c['method']): c for c in report['cells']}
    text = [[_cell_text(by[k, m], k) if (k, m) in by else '' for m in methods] for k in keys]
    colours = [[_COLOURS.get(by[k, m]['status'], 'white') if (k, m) in by else 'white'
                for m in methods] for k in keys]
    fig_h = 0.6 * (len(keys) + 1)
    fig, ax = plt.subplots(figsize=(2.0 + 3.2 * len(methods), fig_h))
    ax.axis('off')
    table = ax.table(cellText=text, cellColours=colours, rowLabels=keys, colLabels=methods,
                     loc='upper center', cellLoc='left')
    table.auto_set_font_size(False)
    table.set_fontsize(6.5)
    table.scale(1.0, 3.3)       # four lines of text per cell
    ax.set_title(f'feeder_sim stability: {"PASSED" if report["passed"] else "FAILED"}'
                 + (f' (solver overrides {report["solver_overrides"]})'
                    if report.get('solver_overrides') else ''), fontsize=10)
    fig.savefig(path, dpi=130, bbox_inches='tight')
    plt.close(fig)
