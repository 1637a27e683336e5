//! The PSNR-against-training-time chart, drawn with plotters into a
//! buffer, encoded as PNG and written atomically.

use std::path::Path;
use std::sync::Once;

use plotters::coord::combinators::BindKeyPoints;
use plotters::prelude::*;
use plotters::style::{FontStyle, register_font};

use super::BenchRow;
use crate::engine::front::write_atomic;
use crate::media::png;

const WIDTH: u32 = 800;
const HEIGHT: u32 = 500;

/// Plotters draws text with fonts registered at run time (no system
/// fonts): DejaVu Sans, embedded in the binary.
fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // The embedded font is valid; a failure would only lose the labels.
        let _ = register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    });
}

/// Ticks at 1, 2 and 5 times the powers of ten in `[lo, hi]`.
fn ticks(lo: f64, hi: f64) -> Vec<f64> {
    let mut out = Vec::new();
    let mut decade = 10f64.powf(lo.log10().floor());
    while decade <= hi && out.len() < 64 {
        for m in [1.0, 2.0, 5.0] {
            // Rounded so that labels read 0.2, not 0.20000000000000001.
            let t = format!("{:.6}", m * decade).parse().unwrap_or(m * decade);
            if (lo..=hi).contains(&t) {
                out.push(t);
            }
        }
        decade *= 10.0;
    }
    out
}

pub fn psnr_vs_time(path: &Path, rows: &[BenchRow]) -> anyhow::Result<()> {
    register_fonts();
    let mut models: Vec<&str> = Vec::new();
    for r in rows {
        if !models.contains(&r.model.as_str()) {
            models.push(&r.model);
        }
    }
    let pts = |m: &str| -> Vec<(f64, f64)> {
        rows.iter()
            .filter(|r| r.model == m && r.psnr.is_finite() && r.train_seconds > 0.0)
            .map(|r| (r.train_seconds, r.psnr))
            .collect()
    };
    let all: Vec<(f64, f64)> = models.iter().flat_map(|m| pts(m)).collect();
    let (mut x0, mut x1) = all.iter().fold((f64::INFINITY, 0.0f64), |(a, b), p| (a.min(p.0), b.max(p.0)));
    let (mut y0, mut y1) = all.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.1), b.max(p.1)));
    if all.is_empty() {
        (x0, x1, y0, y1) = (1.0, 10.0, 0.0, 40.0);
    }
    // Some room around the data; a decade at least on the x axis.
    (x0, x1) = (x0 / 1.2, (x1 * 1.2).max(x0 * 10.0));
    (y0, y1) = ((y0 - 1.0).floor(), (y1 + 1.0).ceil());

    let mut buf = vec![0u8; (WIDTH * HEIGHT * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (WIDTH, HEIGHT)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption("Test PSNR against training time", ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(55)
            .build_cartesian_2d((x0..x1).log_scale().with_key_points(ticks(x0, x1)), y0..y1)?;
        chart
            .configure_mesh()
            .max_light_lines(0)
            .x_label_formatter(&|x| format!("{x}"))
            .y_label_formatter(&|y| format!("{y:.0}"))
            .x_desc("training time (s, log scale)")
            .y_desc("test PSNR (dB)")
            .label_style(("sans-serif", 14))
            .draw()?;
        let colours = [RGBColor(31, 119, 180), RGBColor(214, 39, 40), RGBColor(44, 160, 44), RGBColor(148, 103, 189)];
        for (k, m) in models.iter().enumerate() {
            let c = colours[k % colours.len()];
            let p = pts(m);
            chart
                .draw_series(LineSeries::new(p.clone(), c.stroke_width(2)))?
                .label(*m)
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
            chart.draw_series(p.into_iter().map(|xy| Circle::new(xy, 4, c.filled())))?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()?;
        root.present()?;
    }
    let bytes = png::encode_rgb(WIDTH, HEIGHT, &buf)?;
    write_atomic(path, &bytes)?;
    Ok(())
}
