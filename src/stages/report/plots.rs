//! The report's charts, drawn with `plotters` into inline SVG (text stays text, so the page
//! needs no fonts and scales without blur): grouped bars of a metric per view range and
//! method, and training curves of every loss term on a log scale.

use plotters::coord::Shift;
use plotters::prelude::*;

/// A qualitative palette (Tableau 10), one colour per method or curve.
pub const PALETTE: [RGBColor; 10] = [
    RGBColor(78, 121, 167),
    RGBColor(242, 142, 43),
    RGBColor(225, 87, 89),
    RGBColor(118, 183, 178),
    RGBColor(89, 161, 79),
    RGBColor(237, 201, 72),
    RGBColor(176, 122, 161),
    RGBColor(255, 157, 167),
    RGBColor(156, 117, 95),
    RGBColor(186, 176, 172),
];

fn plot_err<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> anyhow::Error {
    anyhow::anyhow!("drawing a chart: {e}")
}

/// Draw the legend of `chart`'s series at `position` (on a light box) and finish `root`.
fn legend_and_present<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    root: &DrawingArea<DB, Shift>,
    chart: &mut ChartContext<'a, DB, CT>,
    position: SeriesLabelPosition,
) -> anyhow::Result<()> {
    chart
        .configure_series_labels()
        .position(position)
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .draw()
        .map_err(plot_err)?;
    root.present().map_err(plot_err)
}

/// Grouped bars: `values[g][m]` is method `m`'s value in group `g` (`None`: no bar).
pub fn grouped_bars(
    title: &str,
    y_label: &str,
    groups: &[String],
    methods: &[String],
    values: &[Vec<Option<f64>>],
) -> anyhow::Result<String> {
    let present = values.iter().flatten().flatten().copied();
    let (lo, hi) =
        present.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    anyhow::ensure!(lo.is_finite() && hi.is_finite(), "chart '{title}' has no finite value");
    // Bars start at a floor below the smallest value so differences stay visible.
    let pad = ((hi - lo) * 0.15).max(hi.abs() * 0.02).max(1e-6);
    let (y0, y1) = (if lo >= 0.0 && lo - pad * 3.0 < 0.0 { 0.0 } else { lo - pad * 3.0 }, hi + pad);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (640, 340)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..groups.len() as f64, y0..y1)
            .map_err(plot_err)?;
        let names = groups.to_vec();
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(groups.len() * 2 + 1)
            .x_label_formatter(&move |x| {
                let g = x.floor() as usize;
                if (x - g as f64 - 0.5).abs() < 1e-6 {
                    names.get(g).cloned().unwrap_or_default()
                } else {
                    String::new()
                }
            })
            .y_desc(y_label)
            .draw()
            .map_err(plot_err)?;
        let width = 0.8 / methods.len().max(1) as f64;
        for (m, name) in methods.iter().enumerate() {
            let color = PALETTE[m % PALETTE.len()];
            let bars = values.iter().enumerate().filter_map(|(g, row)| {
                let v = row.get(m).copied().flatten()?;
                let x0 = g as f64 + 0.1 + m as f64 * width;
                Some(Rectangle::new([(x0, y0), (x0 + width * 0.9, v)], color.filled()))
            });
            chart.draw_series(bars).map_err(plot_err)?.label(name.as_str()).legend(
                move |(x, y)| Rectangle::new([(x, y - 5), (x + 10, y + 5)], color.filled()),
            );
        }
        legend_and_present(&root, &mut chart, SeriesLabelPosition::LowerRight)?;
    }
    Ok(svg)
}

/// A named curve of `(step, value)` points.
pub type Curve = (String, Vec<(f64, f64)>);

/// Curves `(name, [(step, value)])` on a log-scale y axis; non-positive or non-finite
/// values are left out (a log axis cannot show them).
pub fn log_curves(title: &str, curves: &[Curve]) -> anyhow::Result<String> {
    let points =
        curves.iter().flat_map(|(_, c)| c.iter()).filter(|(_, v)| v.is_finite() && *v > 0.0);
    let (mut x1, mut lo, mut hi) = (1.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, v) in points {
        x1 = x1.max(x);
        lo = lo.min(v);
        hi = hi.max(v);
    }
    anyhow::ensure!(lo.is_finite(), "chart '{title}' has no positive value");
    let (lo, hi) = (lo * 0.8, hi * 1.25);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (640, 360)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(10)
            .x_label_area_size(30)
            .y_label_area_size(70)
            .build_cartesian_2d(0f64..x1, (lo..hi).log_scale())
            .map_err(plot_err)?;
        chart.configure_mesh().x_desc("step").y_desc("loss").draw().map_err(plot_err)?;
        for (i, (name, c)) in curves.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let pts = c.iter().copied().filter(|(_, v)| v.is_finite() && *v > 0.0);
            chart
                .draw_series(LineSeries::new(pts, color.stroke_width(2)))
                .map_err(plot_err)?
                .label(name.as_str())
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 14, y)], color.stroke_width(2))
                });
        }
        legend_and_present(&root, &mut chart, SeriesLabelPosition::UpperRight)?;
    }
    Ok(svg)
}

/// A horizontal colour bar of `colormap` from `lo` to `hi`, labelled `label`.
pub fn colour_bar(
    label: &str,
    lo: f64,
    hi: f64,
    colormap: fn(f64) -> [f32; 3],
) -> anyhow::Result<String> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (420, 90)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let mut chart = ChartBuilder::on(&root)
            .margin(8)
            .x_label_area_size(40)
            .build_cartesian_2d(lo..hi, 0f64..1f64)
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .disable_y_axis()
            .x_labels(5)
            .x_label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 14))
            .x_desc(label)
            .draw()
            .map_err(plot_err)?;
        let n = 64;
        let cells = (0..n).map(|k| {
            let (a, b) = (k as f64 / n as f64, (k + 1) as f64 / n as f64);
            let [r, g, bl] = colormap((a + b) / 2.0);
            let c = RGBColor((r * 255.0) as u8, (g * 255.0) as u8, (bl * 255.0) as u8);
            Rectangle::new([(lo + a * (hi - lo), 0.0), (lo + b * (hi - lo), 1.0)], c.filled())
        });
        chart.draw_series(cells).map_err(plot_err)?;
        root.present().map_err(plot_err)?;
    }
    Ok(svg)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_are_svg_with_their_labels() {
        let groups = vec!["(0°, 60°]".to_string(), "(60°, 120°]".to_string()];
        let methods = vec!["base".to_string(), "usplat4d".to_string()];
        let svg = grouped_bars(
            "PSNR",
            "dB",
            &groups,
            &methods,
            &[vec![Some(20.0), Some(21.0)], vec![Some(18.0), None]],
        )
        .unwrap();
        assert!(svg.starts_with("<svg") && svg.contains("usplat4d") && svg.contains("PSNR"));
        assert!(svg.matches("<rect").count() >= 3);
        let curves = vec![("l1".to_string(), vec![(0.0, 1.0), (10.0, 0.1), (20.0, -1.0)])];
        let svg = log_curves("loss", &curves).unwrap();
        assert!(svg.contains("<polyline") || svg.contains("<path"));
        assert!(log_curves("empty", &[("x".into(), vec![(0.0, 0.0)])]).is_err());
    }
}
