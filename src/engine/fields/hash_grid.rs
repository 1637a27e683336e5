//! The fast model's field (Instant-NGP): the hash-grid networks (`nets`: a
//! multiresolution hash grid, a tiny density MLP whose first output is
//! log-density and the rest geometry features, and a tiny colour MLP on those
//! features and the spherical-harmonics encoding of the direction) over a box
//! of model space, mapped to the unit cube the grid covers. Its density is
//! `exp(clamp(raw))`; its last colour layer is the GEMM one
//! (`ColorHead::Gemm`).

pub use super::nets::Ctx;
use super::nets::{ColorHead, Nets};
use super::{Field, Points};
use crate::engine::geometry::math::Vec3;
use crate::engine::nn::hashgrid::HashGridConfig;
use crate::engine::nn::linear::ParamLayout;
use crate::engine::rng::Rng;

/// The hash-grid field over a box of model space (mapped to the unit cube
/// the grid covers).
pub struct HashGridField {
    nets: Nets,
    lo: Vec3,
    inv: Vec3,
}

impl HashGridField {
    /// Lays out the field's parameters in `layout`: the hash grid, then
    /// `density.0-1` and `color.0-2`.
    pub fn new(
        layout: &mut ParamLayout,
        grid: HashGridConfig,
        hidden: usize,
        geo_features: usize,
        aabb: (Vec3, Vec3),
    ) -> Self {
        let nets = Nets::new(layout, grid, hidden, geo_features, ColorHead::Gemm, 1.0);
        let (lo, hi) = aabb;
        let ext = hi - lo;
        Self { nets, lo, inv: Vec3::new(1.0 / ext.x, 1.0 / ext.y, 1.0 / ext.z) }
    }

    /// Initialises the field's ranges of `params`.
    pub fn init(&self, params: &mut [f32], rng: &mut Rng) {
        self.nets.init(params, rng);
    }

    /// [`Field::backward`] (the same parameter gradients), and also the
    /// gradients with respect to the inputs of the last density pass (after
    /// any [`Field::compact`]) and colour pass: read them with
    /// [`HashGridField::input_grads`]. `dirs` are the directions the colour
    /// pass was given (`[n x 3]`). Not for colours from
    /// [`Field::color_rows`], which keep no positions.
    ///
    /// The positions' gradient flows through both outputs: the density and
    /// the colour's geometry features both come from the hash grid
    /// ([`HashGrid::backward_with_input_grad`](crate::engine::nn::hashgrid::HashGrid::backward_with_input_grad)),
    /// then through the box map `u = (x - lo) / (hi - lo)`. The directions'
    /// gradient comes from the colour network's spherical-harmonics input
    /// ([`sh::encode_backward`](crate::engine::nn::sh::encode_backward)).
    pub fn backward_with_input_grads(
        &self,
        params: &[f32],
        ctx: &mut Ctx,
        dirs: &[f32],
        dsigma: &[f32],
        drgb: &[f32],
        grads: &mut [f32],
    ) {
        self.nets.backward(params, ctx, dsigma, drgb, grads, Some(dirs));
        let inv = self.inv;
        self.nets.position_grads(ctx, |_, du| [du[0] * inv.x, du[1] * inv.y, du[2] * inv.z]);
    }

    /// dL/d(position) (model space) and dL/d(direction), `[n x 3]` each, of
    /// the last [`HashGridField::backward_with_input_grads`].
    pub fn input_grads<'c>(&self, ctx: &'c Ctx) -> (&'c [f32], &'c [f32]) {
        self.nets.input_grads(ctx)
    }
}

impl Field for HashGridField {
    type Ctx = Ctx;

    fn density(&self, params: &[f32], pts: Points<'_>, ctx: &mut Ctx) {
        let (lo, inv) = (self.lo, self.inv);
        ctx.unit.clear();
        for q in pts.pos.chunks_exact(3) {
            let p = Vec3::new(q[0], q[1], q[2]) - lo;
            ctx.unit.extend_from_slice(&[p.x * inv.x, p.y * inv.y, p.z * inv.z]);
        }
        ctx.n = pts.pos.len() / 3;
        self.nets.forward_density(params, ctx);
    }

    fn compact(&self, ctx: &mut Ctx, keep: &[usize]) {
        self.nets.compact(ctx, keep);
    }

    fn color(&self, params: &[f32], dirs: &[f32], ctx: &mut Ctx) {
        self.nets.forward_color(params, dirs, ctx, |_| {});
    }

    fn sigma<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        self.nets.sigma(ctx)
    }

    fn rgb<'c>(&self, ctx: &'c Ctx) -> &'c [f32] {
        self.nets.rgb(ctx)
    }

    fn save_row(&self, ctx: &Ctx, i: usize, rows: &mut Vec<f32>) {
        self.nets.save_row(ctx, i, rows);
    }

    fn color_rows(&self, params: &[f32], rows: Vec<f32>, dirs: &[f32], ctx: &mut Ctx) {
        self.nets.color_rows(params, rows, dirs, ctx, |_| {});
    }

    fn backward(&self, params: &[f32], ctx: &mut Ctx, dsigma: &[f32], drgb: &[f32], grads: &mut [f32]) {
        self.nets.backward(params, ctx, dsigma, drgb, grads, None);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Random points of the box `lo..hi` whose unit-cube coordinates keep
    /// `margin` cells clear of the cell faces of every resolution up to
    /// `max_res` (the hash grid's derivative jumps on faces).
    fn points_off_faces(rng: &mut Rng, count: usize, lo: Vec3, hi: Vec3, max_res: u32, margin: f32) -> Vec<f32> {
        let mut pts = Vec::with_capacity(3 * count);
        while pts.len() < 3 * count {
            let u = [rng.f32(), rng.f32(), rng.f32()];
            let clear = (1..=max_res).all(|r| {
                u.iter().all(|&v| {
                    let x = v * r as f32;
                    (x - x.round()).abs() > margin
                })
            });
            if clear {
                let (lo, ext) = (lo.to_array(), (hi - lo).to_array());
                pts.extend((0..3).map(|a| lo[a] + u[a] * ext[a]));
            }
        }
        pts
    }

    /// dL/dx and dL/d(direction) of `L = Σ gs σ + Σ gc rgb` through the whole
    /// field (density, compaction, colour) against central differences of
    /// its f32 forward passes; the parameter gradients stay `backward`'s.
    #[test]
    fn input_gradients_through_the_field_match_finite_differences() {
        let grid = HashGridConfig { levels: 3, log2_table: 6, base_resolution: 2, finest_resolution: 8 };
        // A box that is not a cube, so the box map's scales matter.
        let (lo, hi) = (Vec3::new(-1.0, -2.0, -0.5), Vec3::new(1.0, 2.0, 1.5));
        let mut layout = ParamLayout::default();
        let field = HashGridField::new(&mut layout, grid, 8, 4, (lo, hi));
        let mut rng = Rng::new(7);
        let mut params = vec![0.0f32; layout.len];
        field.init(&mut params, &mut rng);
        for p in params.iter_mut() {
            *p += 0.3 * rng.normal();
        }
        let n = 7;
        let pos = points_off_faces(&mut rng, n, lo, hi, 8, 0.05);
        let dirs: Vec<f32> = (0..3 * n).map(|_| rng.normal()).collect();
        let keep = [0usize, 2, 3, 5, 6];
        let kept_dirs: Vec<f32> = keep.iter().flat_map(|&i| dirs[3 * i..3 * i + 3].to_vec()).collect();
        let gs: Vec<f32> = keep.iter().map(|_| rng.normal() * 0.1).collect();
        let gc: Vec<f32> = (0..3 * keep.len()).map(|_| rng.normal()).collect();
        let run = |pos: &[f32], kd: &[f32]| -> (f64, Ctx) {
            let mut ctx = Ctx::default();
            field.density(&params, Points { pos, dirs: &dirs, image: &[] }, &mut ctx);
            field.compact(&mut ctx, &keep);
            field.color(&params, kd, &mut ctx);
            let v = field.sigma(&ctx).iter().zip(&gs).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>()
                + field.rgb(&ctx).iter().zip(&gc).map(|(a, b)| *a as f64 * *b as f64).sum::<f64>();
            (v, ctx)
        };
        let (_, mut ctx) = run(&pos, &kept_dirs);
        let mut grads = vec![0.0f32; layout.len];
        field.backward_with_input_grads(&params, &mut ctx, &kept_dirs, &gs, &gc, &mut grads);
        let (dpos, ddirs) = field.input_grads(&ctx);
        assert_eq!((dpos.len(), ddirs.len()), (3 * keep.len(), 3 * keep.len()));

        let (_, mut plain) = run(&pos, &kept_dirs);
        let mut want = vec![0.0f32; layout.len];
        field.backward(&params, &mut plain, &gs, &gc, &mut want);
        assert!(grads.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "parameter gradients differ");

        let h = 1e-3f32;
        let check = |what: &str, got: &[f32], input: &[f32], rows: &[usize], eval: &dyn Fn(&[f32]) -> f64| {
            let mut largest = 0.0f64;
            for (j, &i) in rows.iter().enumerate() {
                for a in 0..3 {
                    let (mut up, mut down) = (input.to_vec(), input.to_vec());
                    up[3 * i + a] += h;
                    down[3 * i + a] -= h;
                    let step = (up[3 * i + a] - down[3 * i + a]) as f64;
                    let num = (eval(&up) - eval(&down)) / step;
                    let ana = got[3 * j + a] as f64;
                    largest = largest.max(num.abs());
                    assert!(
                        (num - ana).abs() < 2e-3 + 2e-2 * num.abs(),
                        "{what} of sample {i}, axis {a}: numeric {num}, analytic {ana}"
                    );
                }
            }
            assert!(largest > 0.05, "{what}: every gradient is tiny ({largest})");
        };
        check("dL/dx", dpos, &pos, &keep, &|p| run(p, &kept_dirs).0);
        let all: Vec<usize> = (0..keep.len()).collect();
        check("dL/d(direction)", ddirs, &kept_dirs, &all, &|d| run(&pos, d).0);
    }
}
