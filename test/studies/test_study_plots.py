"""Study plots: axes named by what the parameter is, with units; legends never over data."""

import matplotlib
import numpy as np
import pytest

from feeder_sim.studies import summary as S
from feeder_sim.studies.spec import parse_study

matplotlib.use('Agg')


def speed_map_spec(**extra):
    return parse_study({
        'scene': 'track_one_box', 'duration': 0.1, 'repeats': 2, 'seed': 1,
        'parameters': {'bodies[track].vibration.amplitude': {'range': [1e-4, 5e-4], 'count': 5},
                       'bodies[track].vibration.frequency': [30.0, 40.0, 50.0, 60.0],
                       **extra},
        'metrics': ['conveying_speed_mps'],
        'objective': {'metric': 'conveying_speed_mps', 'goal': 'max'}})


def test_axis_labels_come_from_the_key_path_or_the_study():
    spec = speed_map_spec()
    amplitude, frequency = spec.parameters
    assert S.parameter_label(spec, amplitude) == 'track drive amplitude (m)'
    assert S.parameter_label(spec, frequency) == 'track drive frequency (Hz)'
    own = parse_study({
        'scene': 'track_one_box', 'duration': 0.1, 'repeats': 1, 'seed': 1,
        'parameters': {'bodies[box].mu_static': {'values': [0.6, 0.8],
                                                 'label': 'box friction', 'unit': '-'}},
        'metrics': ['conveying_speed_mps']})
    assert S.parameter_label(own, own.parameters[0]) == 'box friction (-)'
    assert S.metric_label('conveying_speed_mps') == 'conveying speed (m/s)'
    assert S.metric_label('feed_rate_per_min') == 'feed rate (1/min)'
    assert S.metric_label('fraction:open_end_up') == 'fraction: open end up'


@pytest.mark.parametrize('best_corner', ['top right', 'top left', 'bottom right', 'bottom left'])
def test_the_legend_covers_no_data(tmp_path, monkeypatch, best_corner):
    # the best design in each corner of the map in turn (where a legend inside the axes sits)
    spec = speed_map_spec()
    amplitudes, frequencies = (p.values for p in spec.parameters)
    ix = len(amplitudes) - 1 if 'right' in best_corner else 0
    iy = len(frequencies) - 1 if 'top' in best_corner else 0
    designs = []
    for j, f in enumerate(frequencies):
        for i, a in enumerate(amplitudes):
            mean = 1.0 if (i, j) == (ix, iy) else 0.1 * (i + j) / 10
            designs.append({'design': len(designs), 'parameters': {
                spec.parameters[0].name: a, spec.parameters[1].name: f},
                'metrics': {'conveying_speed_mps': {'mean': mean, 'ci95': [mean, mean]}}})
    best = designs[iy * len(amplitudes) + ix]['design']
    figures = []
    import matplotlib.pyplot as plt
    monkeypatch.setattr(plt, 'close', lambda fig=None: figures.append(fig))
    S.plot(spec, {'designs': designs, 'best_design': best}, [], tmp_path)
    (fig,) = figures
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    (legend,) = fig.legends
    box = legend.get_window_extent(renderer)
    ax = fig.axes[0]
    star = next(line for line in ax.get_lines() if line.get_label().startswith('best'))
    x, y = ax.transData.transform(np.column_stack(star.get_data()))[0]
    assert not box.contains(x, y)
    for axes in fig.axes:            # the map and its colour bar
        assert not box.overlaps(axes.get_window_extent(renderer))
    assert ax.get_xlabel() == 'track drive amplitude (m)'
    assert ax.get_ylabel() == 'track drive frequency (Hz)'
    assert (tmp_path / 'conveying_speed_mps.png').stat().st_size > 10_000
