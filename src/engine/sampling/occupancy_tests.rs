//! Unit tests of `occupancy.rs` (kept apart so the module reads in one sitting).

use super::*;

#[test]
fn separable_dilation_equals_the_27_neighbour_rule() {
    let r = 7isize;
    let mut rng = Rng::new(9);
    let raw: Vec<bool> = (0..r * r * r).map(|_| rng.f32() < 0.04).collect();
    let fast = dilate(&raw, r as usize);
    let idx = |x: isize, y: isize, z: isize| ((x * r + y) * r + z) as usize;
    for x in 0..r {
        for y in 0..r {
            for z in 0..r {
                let mut any = false;
                for (dx, dy, dz) in (0..27).map(|k| (k / 9 - 1, (k / 3) % 3 - 1, k % 3 - 1)) {
                    let (a, b, c) = (x + dx, y + dy, z + dz);
                    any |= (0..r).contains(&a) && (0..r).contains(&b) && (0..r).contains(&c) && raw[idx(a, b, c)];
                }
                assert_eq!(fast[idx(x, y, z)], any, "cell {x},{y},{z}");
            }
        }
    }
    assert!(fast.iter().filter(|&&b| b).count() > raw.iter().filter(|&&b| b).count());
}

/// A grid of two small dense spots in a box of 32^3 cells.
fn spots(dilate: bool) -> OccupancyGrid {
    let r = 32;
    let cfg = OccupancyConfig {
        resolution: r,
        warmup_steps: 0,
        update_every: 1,
        sweep: 1,
        dilate: Some(dilate),
        ..Default::default()
    };
    let mut g = OccupancyGrid::new(cfg, unit());
    let (cells, pts) = g.update_points(1, 3);
    let sigma: Vec<f32> = pts
        .chunks(3)
        .map(|p| {
            let q = Vec3::new(p[0], p[1], p[2]);
            let near = |c: Vec3| (q - c).norm() < 0.08;
            if near(Vec3::new(0.3, -0.2, 0.1)) || near(Vec3::new(-0.7, 0.6, -0.5)) { 100.0 } else { 0.0 }
        })
        .collect();
    g.apply(1, &cells, &sigma);
    g
}

/// A random ray from outside the unit box through a random point of
/// the two-spot grid's box (aimed at a spot half of the time).
fn random_ray(rng: &mut Rng, k: usize) -> Ray {
    let target = match k % 4 {
        0 => Vec3::new(0.3, -0.2, 0.1),
        1 => Vec3::new(-0.7, 0.6, -0.5),
        _ => Vec3::new(rng.f32() * 2.0 - 1.0, rng.f32() * 2.0 - 1.0, rng.f32() * 2.0 - 1.0),
    } + Vec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.03;
    let origin = Vec3::new(rng.normal(), rng.normal(), rng.normal()).normalized().unwrap() * 3.0;
    Ray { origin, dir: (target - origin).normalized().unwrap() }
}

/// Distance in cells from `p` to the nearest face of the cell holding it.
fn to_face(g: &OccupancyGrid, p: Vec3) -> f32 {
    let c = (p - g.aabb.min) * (g.config.resolution as f32 / 2.0);
    [c.x, c.y, c.z].iter().map(|v| (v - v.round()).abs()).fold(f32::INFINITY, f32::min)
}

/// Each mip level's cell is set exactly when a cell inside it is, also
/// for a resolution that is not a power of two.
#[test]
fn mip_levels_are_the_or_of_their_cells() {
    for (res, levels) in [(32, 5), (24, 4), (20, 4), (3, 1)] {
        let cfg = OccupancyConfig { resolution: res, warmup_steps: 0, update_every: 1, sweep: 1, ..Default::default() };
        let mut g = OccupancyGrid::new(cfg, unit());
        let (cells, pts) = g.update_points(1, 3);
        let mut rng = Rng::new(res as u64);
        let sigma: Vec<f32> = pts.chunks(3).map(|_| if rng.f32() < 0.0005 { 100.0 } else { 0.0 }).collect();
        g.apply(1, &cells, &sigma);
        assert_eq!(g.mips.len() + 1, OccupancyGrid::levels(res));
        assert_eq!(OccupancyGrid::levels(res), levels);
        for l in 1..=g.mips.len() {
            let mut set = 0;
            for x in 0..res {
                for y in 0..res {
                    for z in 0..res {
                        let any = (0..res).filter(|i| i >> l == x >> l).any(|i| {
                            (0..res)
                                .filter(|j| j >> l == y >> l)
                                .any(|j| (0..res).filter(|k| k >> l == z >> l).any(|k| g.bits[(i * res + j) * res + k]))
                        });
                        assert_eq!(g.mip_bit(l, [x, y, z]), any, "res {res} level {l} at {x} {y} {z}");
                        set += any as usize;
                    }
                }
            }
            assert!(set > 0 && (l > 2 || set < res * res * res), "level {l}: {set} set");
        }
    }
}

/// What an empty probe steps over (up to its exit) holds no occupied
/// cell, and most steps leave a whole empty block.
#[test]
fn empty_probes_hold_no_occupied_cell() {
    let g = spots(true);
    let r = g.config.resolution;
    let occupied = g.bits.iter().filter(|&&b| b).count();
    assert!((0..r * r * r).all(|c| g.bit(c) == g.bits[c]), "the packed bits are the bits");
    assert!(occupied > 0 && occupied < r * r * r / 10, "{occupied}");
    let mut rng = Rng::new(11);
    let (mut empty, mut long) = (0, 0);
    for k in 0..400 {
        let ray = random_ray(&mut rng, k);
        let gr = g.grid_ray(&ray);
        let t = 2.0 + 2.0 * rng.f32();
        match g.probe(&gr, t) {
            Probe::Empty { exit } => {
                assert!(exit >= t, "exit {exit} before t {t}");
                assert!(!g.occupied(ray.at(t)));
                empty += 1;
                long += (exit - t > 4.0 / r as f32) as usize;
                for i in 0..64 {
                    let p = ray.at(t + (exit - t) * i as f32 / 64.0);
                    assert!(!g.occupied(p) || to_face(&g, p) < 1e-3, "ray {k}: occupied cell at {p:?} before {exit}");
                }
            }
            Probe::Occupied { exit } => {
                assert!(g.occupied(ray.at(t)) && exit >= t);
                let mid = ray.at(0.5 * (t + exit));
                assert!(g.occupied(mid) || to_face(&g, mid) < 1e-3);
            }
            Probe::Outside => assert!(g.cell_of(ray.at(t)).is_none()),
        }
    }
    assert!(empty > 200 && long > empty / 2, "{empty} empty probes, {long} leave a block");
}

/// Marching takes exactly the lattice points that lie in occupied cells
/// (but for points within rounding of a cell face), whatever `limit`
/// splits the march into.
#[test]
fn marching_takes_every_occupied_lattice_point() {
    for dilate in [true, false] {
        marching_matches_brute_force(&spots(dilate));
    }
}

fn marching_matches_brute_force(g: &OccupancyGrid) {
    let mut rng = Rng::new(12);
    let dt = 0.013;
    let mut total = 0;
    for k in 0..300 {
        let ray = random_ray(&mut rng, k);
        let (t0, t1) = (1.5 + 0.5 * rng.f32(), 4.5);
        let brute: Vec<i64> = (0..)
            .map(|i| (i, t0 + i as f32 * dt))
            .take_while(|&(_, t)| t < t1)
            .filter(|&(_, t)| g.occupied(ray.at(t)) && g.cell_of(ray.at(t)).is_some())
            .map(|(i, _)| i)
            .collect();
        let gr = g.grid_ray(&ray);
        let limit = 1 + k % 20;
        let mut got = Vec::new();
        let mut t = t0;
        loop {
            let before = got.len();
            let (n, _) = g.march(&gr, &mut t, t1, dt, limit, |s| got.push(s));
            assert_eq!(n, got.len() - before);
            assert!(n <= limit);
            if n == 0 {
                break;
            }
        }
        assert!(t >= t1);
        let got: Vec<i64> = got.iter().map(|&s| ((s - t0) / dt).round() as i64).collect();
        assert!(got.windows(2).all(|w| w[0] < w[1]), "ray {k}: samples in order");
        let near_face = |i: i64| to_face(g, ray.at(t0 + i as f32 * dt)) < 2e-3;
        for i in &brute {
            assert!(got.contains(i) || near_face(*i), "ray {k}: occupied lattice point {i} skipped");
        }
        for i in &got {
            assert!(brute.contains(i) || near_face(*i), "ray {k}: lattice point {i} is empty");
        }
        total += brute.len();
    }
    assert!(total > 500, "the rays cross the spots: {total} occupied points");
}

/// Far along a ray, where the step is below f32 resolution, marching
/// ends instead of looping or repeating a point.
#[test]
fn marching_far_along_a_ray_terminates() {
    let mut g = spots(true);
    let ray = Ray { origin: Vec3::new(0.3, -0.2, 4e7), dir: Vec3::new(0.0, 0.0, -1.0) };
    let gr = g.grid_ray(&ray);
    for active in [true, false] {
        g.active = active;
        // 4e7 is the only f32 in the box along this ray (the next one
        // is 4e7 + 4), and 4e7 + 0.01 == 4e7.
        let (t0, t1) = (4e7f32, 4e7f32 + 4.0);
        assert!(t0 < t1 && t0 + 0.01 == t0 && g.cell_of(ray.at(t0)).is_some());
        let mut t = t0;
        let mut got = Vec::new();
        let (n, _) = g.march(&gr, &mut t, t1, 0.01, 1000, |s| got.push(s));
        assert!(n == got.len() && n <= 1 && t >= t1, "{n} samples, t {t}");
        assert!(active || n == 1, "before warm-up the point is sampled");
        // Outside the box the whole way.
        let mut t = 1e8;
        let (n, _) = g.march(&gr, &mut t, 1e8 + 100.0, 0.01, 1000, |_| {});
        assert_eq!((n, t), (0, 1e8 + 100.0));
    }
}

/// Before the warm-up every lattice point in the box is a sample.
#[test]
fn marching_before_warm_up_takes_every_point() {
    let g = OccupancyGrid::new(OccupancyConfig::default(), unit());
    let ray = Ray { origin: Vec3::new(-3.0, 0.1, 0.2), dir: Vec3::new(1.0, 0.0, 0.0) };
    let mut t = 1.0;
    let mut got = Vec::new();
    let (n, skipped) = g.march(&g.grid_ray(&ray), &mut t, 5.0, 0.01, 10_000, |s| got.push(s));
    assert_eq!(skipped, 0);
    // Inside the box: t in [2, 4).
    assert!((199..=201).contains(&n), "{n}");
    assert!(got.iter().all(|&s| (1.99..4.0).contains(&s)));
}

fn unit() -> Aabb {
    Aabb { min: Vec3::splat(-1.0), max: Vec3::splat(1.0) }
}

#[test]
fn segments_map_occupied_length_to_distance() {
    let mut s = Segments::default();
    s.push(1.0, 2.0);
    s.push(2.0, 2.5); // merges
    s.push(4.0, 5.0);
    assert_eq!(s.spans, vec![(1.0, 2.5), (4.0, 5.0)]);
    assert!((s.length() - 2.5).abs() < 1e-6);
    assert_eq!(s.to_t(0.0), 1.0);
    assert!((s.to_t(1.0) - 2.0).abs() < 1e-6);
    assert!((s.to_t(2.0) - 4.5).abs() < 1e-6);
    assert_eq!(s.to_t(9.0), 5.0);
}

#[test]
fn a_dense_ball_is_never_skipped() {
    let cfg = OccupancyConfig { resolution: 16, warmup_steps: 0, update_every: 1, sweep: 1, ..Default::default() };
    let mut g = OccupancyGrid::new(cfg, unit());
    let (cells, pts) = g.update_points(1, 3);
    let sigma: Vec<f32> =
        pts.chunks(3).map(|p| if Vec3::new(p[0], p[1], p[2]).norm() < 0.3 { 50.0 } else { 0.0 }).collect();
    g.apply(1, &cells, &sigma);
    assert!(g.active);
    assert!(g.occupancy() < 0.2, "most cells are empty: {}", g.occupancy());
    // Every point of the ball is in an occupied cell...
    let mut rng = Rng::new(5);
    for _ in 0..2000 {
        let p = Vec3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5) * 0.6;
        if p.norm() < 0.3 {
            assert!(g.occupied(p), "{p:?}");
        }
    }
    // ... and a ray through the ball keeps the ball's whole chord.
    let ray = Ray { origin: Vec3::new(-3.0, 0.05, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
    let s = g.segments(&ray, 2.0, 4.0);
    let chord = (0.3f32 * 0.3 - 0.05 * 0.05).sqrt();
    assert!(s.spans.iter().any(|&(a, b)| a <= 3.0 - chord && b >= 3.0 + chord), "{:?}", s.spans);
    assert!(s.length() < 1.5, "empty space skipped: {}", s.length());
    // A ray that misses the ball by far has nothing to sample.
    let miss = Ray { origin: Vec3::new(-3.0, 0.9, 0.9), dir: Vec3::new(1.0, 0.0, 0.0) };
    assert_eq!(g.segments(&miss, 2.0, 4.0).length(), 0.0);
}

#[test]
fn rays_from_far_away_terminate() {
    let cfg = OccupancyConfig { resolution: 32, warmup_steps: 0, ..Default::default() };
    let mut g = OccupancyGrid::new(cfg, unit());
    g.apply(1, &[], &[]);
    // At t = 4e6 an f32 step is 0.25 or 0.5, more than twice the marching step.
    let ray = Ray { origin: Vec3::new(0.0, 0.0, 4e6), dir: Vec3::new(0.0, 0.0, -1.0) };
    let s = g.segments(&ray, 4e6 - 1.0, 4e6 + 1.0);
    assert!(s.length() > 0.0 && s.length() <= 2.0, "{s:?}");
}

#[test]
fn before_warm_up_everything_is_sampled() {
    let g = OccupancyGrid::new(OccupancyConfig::default(), unit());
    let ray = Ray { origin: Vec3::new(-3.0, 0.0, 0.0), dir: Vec3::new(1.0, 0.0, 0.0) };
    assert_eq!(g.segments(&ray, 2.0, 4.0), Segments::single(2.0, 4.0));
}
