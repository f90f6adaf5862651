//! Desire lines: where people walk between two points, learned from their
//! walks, as a model any runtime can run.
//!
//! The model is a kernel regression over the training walks' shapes,
//! conditioned on the requested endpoints by their coordinates (cell units,
//! cell `(x, y)` spanning `[x, x+1) × [y, y+1)`), so it serves any pair of
//! points, on grids of any size: its input is 4 numbers and a prior line,
//! not a frame.
//!
//! Each training walk (in both directions) is stored as its end cells'
//! centres `(a_i, b_i)` and its shape `u_i(s)` at [`POINTS`] fractions `s` of
//! its length, as complex numbers normalised so the walk runs from 0 to 1:
//! `u_i(s) = (z_i(s) − z_i(0)) / (z_i(1) − z_i(0))`. A request `a → b`
//! weighs every walk by how near its ends are, `w_i = exp(−|x − e_i|² /
//! 2σ²)` over the four coordinates, and averages their shapes together with the shape `p(s)` of a prior line (the planner
//! passes the profile's any-angle route: what it would serve without walks)
//! counted as one more walk of weight `π`: `ū = (Σ w_i u_i + π p) / (Σ w_i +
//! π)` (a walk's shape mapped onto the request's ends by the similarity that
//! takes its ends there, averaged). The average is then shrunk towards the
//! prior, point by point, by how much the walks agree: with `μ = ū − p`,
//! the spread `v` of the shapes around `ū` and their effective number `n =
//! (Σw + π)² / (Σw² + π²)`, `u = p + λ μ`, `λ = |μ|² / (|μ|² + c · v / n)`.
//! Where few walks are near, or they bend both ways, the line stays the
//! prior; where many agree, it bends as they do. Below a kernel mass `Σw`
//! of `τ` the walks are not used at all: the answer is the prior, and the
//! model says so. `σ`, `c`, `π` and `τ` are chosen by cross-validation on
//! the training walks (`train::desire`).
//!
//! The ONNX graph ([`DesireLines::to_onnx`]) computes exactly this with the
//! bank as constants: inputs `endpoints` `[N, 4]` (`ax, ay, bx, by`) and
//! `prior` `[N, 2·P]` (the prior line's `P` x then `P` y, cell units, from `a`
//! to `b`, points evenly spaced by length); output `line` `[N, 2·P + 1]`: the
//! line's `P` x then `P` y coordinates, then the walks' share of the answer
//! (`Σw / (Σw + π)`, 0 when the prior alone answered). [`DesireLines::predict`]
//! is the same arithmetic in Rust, which training uses to cross-validate:
//! the kernel sums ([`Sums`]) depend on `σ` alone, so it computes them once
//! per `σ` and finishes them ([`finish`]) for every `c`, `π` and `τ`.
//!
//! Every bank line enters the sums (two products of the request with the
//! bank, 4 × M and M × 3P, as dense matrix products): at waldo's 4,800
//! lines that is cheaper than picking the nearest lines first (ONNX `TopK`
//! over M costs tract ~4× the products), and lines far from the request
//! weigh nothing (their weights underflow to 0).

use tract_onnx::pb;

use super::Metadata;
use super::export::{self, node};

/// Points per line, both ends included (16 segments).
pub const POINTS: usize = 17;

/// The settings cross-validation chooses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Settings {
    /// Kernel width σ over endpoint coordinates, cells.
    pub sigma_cells: f32,
    /// Shrinkage `c` towards the prior.
    pub shrink: f32,
    /// Weight `π` of the prior line in the average, as if one more walk.
    pub prior_weight: f32,
    /// Kernel mass `τ` the walks must exceed to be used at all.
    pub min_mass: f32,
}

/// The learned desire-line model: the walks' ends and shapes, and the
/// settings cross-validation chose.
#[derive(Clone, Debug, PartialEq)]
pub struct DesireLines {
    /// `[ax, ay, bx, by]` per walk direction, cell units.
    pub ends: Vec<[f32; 4]>,
    /// The normalised shape per walk direction: (re, im) at each fraction.
    pub shapes: Vec<[[f32; 2]; POINTS]>,
    pub settings: Settings,
}

/// One answer: the line, and how much of it the walks made.
#[derive(Clone, Debug, PartialEq)]
pub struct Prediction {
    /// [`POINTS`] points from `a` to `b`, cell units.
    pub points: Vec<[f32; 2]>,
    /// The walks' share `Σw / (Σw + π)` of the average; 0 when their mass
    /// was at most `τ` and the prior alone answered.
    pub learned: f32,
    /// The kernel mass `Σw` of the walks.
    pub mass: f32,
}

/// A request's kernel sums over the bank at one `σ`: everything of the
/// answer that does not depend on `c`, `π` or `τ`.
#[derive(Clone, Debug, PartialEq)]
pub struct Sums {
    /// `Σw` and `Σw²`.
    pub mass: f32,
    pub mass_sq: f32,
    /// Per point: `Σw·re`, `Σw·im`, `Σw·|u|²` of the shapes.
    pub points: [[f32; 3]; POINTS],
}

/// The fraction of the way along a line of point `k`.
#[cfg(test)]
pub(crate) fn fraction(k: usize) -> f32 {
    k as f32 / (POINTS - 1) as f32
}

impl DesireLines {
    /// The line from `a` to `b` (cell units), given the `prior` line
    /// ([`POINTS`] points evenly spaced by length from `a` to `b`).
    pub fn predict(&self, a: [f32; 2], b: [f32; 2], prior: &[[f32; 2]]) -> Prediction {
        let sums = self.sums(a, b, self.settings.sigma_cells);
        finish(&self.settings, &sums, a, b, prior)
    }

    /// The kernel sums of the request `a → b` over the bank at `sigma_cells`.
    pub fn sums(&self, a: [f32; 2], b: [f32; 2], sigma_cells: f32) -> Sums {
        let x = [a[0], a[1], b[0], b[1]];
        let scale = 1.0 / (2.0 * sigma_cells * sigma_cells);
        let mut sums = Sums {
            mass: 0.0,
            mass_sq: 0.0,
            points: [[0.0; 3]; POINTS],
        };
        for (e, shape) in self.ends.iter().zip(&self.shapes) {
            let d2: f32 = x.iter().zip(e).map(|(p, q)| (p - q) * (p - q)).sum();
            let w = (-d2 * scale).exp();
            if w == 0.0 {
                continue;
            }
            sums.mass += w;
            sums.mass_sq += w * w;
            for (sum, [ur, ui]) in sums.points.iter_mut().zip(shape) {
                sum[0] += ur * w;
                sum[1] += ui * w;
                sum[2] += (ur * ur + ui * ui) * w;
            }
        }
        sums
    }

    /// The model as an ONNX graph (opset 13) with `meta` as its metadata.
    pub fn to_onnx(&self, meta: &Metadata) -> pb::ModelProto {
        let m = self.ends.len() as i64;
        let p = POINTS as i64;
        let s = &self.settings;
        let mut init = Vec::new();
        // Endpoints transposed [4, M] and their squared norms [1, M].
        let mut ends_t = Vec::with_capacity(4 * self.ends.len());
        for j in 0..4 {
            ends_t.extend(self.ends.iter().map(|e| e[j]));
        }
        init.push(export::tensor("bank.ends_t", &[4, m], &ends_t));
        let ends_sq: Vec<f32> = self
            .ends
            .iter()
            .map(|e| e.iter().map(|v| v * v).sum())
            .collect();
        init.push(export::tensor("bank.ends_sq", &[1, m], &ends_sq));
        // Per line: the shape's real parts, imaginary parts and squared
        // moduli, [M, 3P], weighed by one product.
        let stats: Vec<f32> = self
            .shapes
            .iter()
            .flat_map(|shape| {
                let re = shape.iter().map(|u| u[0]);
                let im = shape.iter().map(|u| u[1]);
                let sq = shape.iter().map(|u| u[0] * u[0] + u[1] * u[1]);
                re.chain(im).chain(sq).collect::<Vec<f32>>()
            })
            .collect();
        init.push(export::tensor("bank.stats", &[m, 3 * p], &stats));
        let scalar = |name: &str, v: f32| export::tensor(name, &[], &[v]);
        init.push(scalar(
            "kernel.scale",
            -1.0 / (2.0 * s.sigma_cells * s.sigma_cells),
        ));
        init.push(scalar("two", 2.0));
        init.push(scalar("shrink", s.shrink));
        init.push(scalar("prior.weight", s.prior_weight));
        init.push(scalar("prior.w2", s.prior_weight * s.prior_weight));
        init.push(scalar("min_mass", s.min_mass));
        init.push(scalar("tiny", TINY));
        let ints = |name: &str, v: i64| pb::TensorProto {
            name: name.to_owned(),
            dims: vec![1],
            data_type: pb::tensor_proto::DataType::Int64 as i32,
            int64_data: vec![v],
            ..Default::default()
        };
        for k in 0..5 {
            init.push(ints(&format!("i{k}"), k));
        }
        for (name, v) in [("p1", p), ("p2", 2 * p), ("p3", 3 * p)] {
            init.push(ints(name, v));
        }
        let mut g = Graph::default();
        let x = "endpoints";
        // Squared distance of the request to every line's ends, [N, M]:
        // |x|² − 2 x·e + |e|², one product with the bank.
        g.op("Mul", &[x, x], "x.sq");
        g.reduce("x.sq", "i1", true, "x.norm");
        g.op("MatMul", &[x, "bank.ends_t"], "x.dot");
        g.op("Mul", &["x.dot", "two"], "x.dot2");
        g.op("Sub", &["x.norm", "x.dot2"], "d2.part");
        g.op("Add", &["d2.part", "bank.ends_sq"], "d2.raw");
        g.op("Relu", &["d2.raw"], "d2");
        // The weights and the weighted sums of the shapes, [N, 3P].
        g.op("Mul", &["d2", "kernel.scale"], "logw");
        g.op("Exp", &["logw"], "w");
        g.op("MatMul", &["w", "bank.stats"], "sums");
        g.op("Mul", &["w", "w"], "w.sq");
        g.reduce("w", "i1", true, "mass");
        g.reduce("w.sq", "i1", true, "mass.sq");
        g.op("Slice", &["sums", "i0", "p1", "i1"], "sum.re");
        g.op("Slice", &["sums", "p1", "p2", "i1"], "sum.im");
        g.op("Slice", &["sums", "p2", "p3", "i1"], "sum.sq");
        // The request's ends, and the prior line as a shape from 0 to 1.
        for (k, name) in ["a.x", "a.y", "b.x", "b.y"].into_iter().enumerate() {
            let (start, end) = (format!("i{k}"), format!("i{}", k + 1));
            g.op("Slice", &[x, &start, &end, "i1"], name);
        }
        g.op("Sub", &["b.x", "a.x"], "d.x");
        g.op("Sub", &["b.y", "a.y"], "d.y");
        g.op("Mul", &["d.x", "d.x"], "d.x2");
        g.op("Mul", &["d.y", "d.y"], "d.y2");
        g.op("Add", &["d.x2", "d.y2"], "chord2.raw");
        g.op("Add", &["chord2.raw", "tiny"], "chord2");
        g.op("Slice", &["prior", "i0", "p1", "i1"], "prior.x");
        g.op("Slice", &["prior", "p1", "p2", "i1"], "prior.y");
        g.op("Sub", &["prior.x", "a.x"], "rel.x");
        g.op("Sub", &["prior.y", "a.y"], "rel.y");
        g.op("Mul", &["rel.x", "d.x"], "rxdx");
        g.op("Mul", &["rel.y", "d.y"], "rydy");
        g.op("Add", &["rxdx", "rydy"], "pre.num");
        g.op("Div", &["pre.num", "chord2"], "p.re");
        g.op("Mul", &["rel.y", "d.x"], "rydx");
        g.op("Mul", &["rel.x", "d.y"], "rxdy");
        g.op("Sub", &["rydx", "rxdy"], "pim.num");
        g.op("Div", &["pim.num", "chord2"], "p.im");
        // The average with the prior as one more walk of weight π.
        g.op("Add", &["mass", "prior.weight"], "total");
        g.op("Mul", &["p.re", "prior.weight"], "p.re.w");
        g.op("Add", &["sum.re", "p.re.w"], "re.sum");
        g.op("Div", &["re.sum", "total"], "re");
        g.op("Mul", &["p.im", "prior.weight"], "p.im.w");
        g.op("Add", &["sum.im", "p.im.w"], "im.sum");
        g.op("Div", &["im.sum", "total"], "im");
        g.op("Mul", &["p.re", "p.re"], "p.re2");
        g.op("Mul", &["p.im", "p.im"], "p.im2");
        g.op("Add", &["p.re2", "p.im2"], "p.sq");
        g.op("Mul", &["p.sq", "prior.weight"], "p.sq.w");
        g.op("Add", &["sum.sq", "p.sq.w"], "sq.sum");
        g.op("Div", &["sq.sum", "total"], "sq");
        g.op("Mul", &["re", "re"], "re2");
        g.op("Mul", &["im", "im"], "im2");
        g.op("Sub", &["sq", "re2"], "var.part");
        g.op("Sub", &["var.part", "im2"], "var.raw");
        g.op("Relu", &["var.raw"], "var");
        g.op("Mul", &["total", "total"], "total2");
        g.op("Add", &["mass.sq", "prior.w2"], "total.sq");
        g.op("Div", &["total2", "total.sq"], "n_eff");
        // Shrunk towards the prior, and not used at all at mass ≤ τ.
        g.op("Sub", &["re", "p.re"], "mu.re");
        g.op("Sub", &["im", "p.im"], "mu.im");
        g.op("Mul", &["mu.re", "mu.re"], "mu.re2");
        g.op("Mul", &["mu.im", "mu.im"], "mu.im2");
        g.op("Add", &["mu.re2", "mu.im2"], "mu2");
        g.op("Mul", &["var", "shrink"], "var.c");
        g.op("Div", &["var.c", "n_eff"], "noise");
        g.op("Add", &["mu2", "noise"], "denominator.part");
        g.op("Add", &["denominator.part", "tiny"], "denominator");
        g.op("Div", &["mu2", "denominator"], "lambda.raw");
        g.op("Greater", &["mass", "min_mass"], "used.bool");
        g.nodes.push(node(
            "Cast",
            vec!["used.bool".into()],
            "used",
            vec![export::int_attr(
                "to",
                pb::tensor_proto::DataType::Float as i64,
            )],
        ));
        g.op("Mul", &["lambda.raw", "used"], "lambda");
        g.op("Mul", &["lambda", "mu.re"], "shift.re");
        g.op("Add", &["p.re", "shift.re"], "f.re");
        g.op("Mul", &["lambda", "mu.im"], "shift.im");
        g.op("Add", &["p.im", "shift.im"], "f.im");
        g.op("Div", &["mass", "total"], "share");
        g.op("Mul", &["share", "used"], "learned");
        // Onto the request's ends.
        g.op("Mul", &["f.re", "d.x"], "rx");
        g.op("Mul", &["f.im", "d.y"], "iy");
        g.op("Sub", &["rx", "iy"], "px.rel");
        g.op("Add", &["a.x", "px.rel"], "points.x");
        g.op("Mul", &["f.re", "d.y"], "ry");
        g.op("Mul", &["f.im", "d.x"], "ix");
        g.op("Add", &["ry", "ix"], "py.rel");
        g.op("Add", &["a.y", "py.rel"], "points.y");
        g.nodes.push(node(
            "Concat",
            vec!["points.x".into(), "points.y".into(), "learned".into()],
            "line",
            vec![export::int_attr("axis", 1)],
        ));
        export::model_proto(
            meta,
            g.nodes,
            init,
            vec![
                export::value_info(x, 4),
                export::value_info("prior", 2 * POINTS),
            ],
            vec![export::value_info("line", 2 * POINTS + 1)],
        )
    }
}

/// Nodes of a graph under construction.
#[derive(Default)]
struct Graph {
    nodes: Vec<pb::NodeProto>,
}

impl Graph {
    fn op(&mut self, op: &str, inputs: &[&str], out: &str) {
        self.nodes.push(node(
            op,
            inputs.iter().map(|s| s.to_string()).collect(),
            out,
            Vec::new(),
        ));
    }

    /// `ReduceSum` of `input` over the axes in the tensor `axes`.
    fn reduce(&mut self, input: &str, axes: &str, keep: bool, out: &str) {
        self.nodes.push(node(
            "ReduceSum",
            vec![input.into(), axes.into()],
            out,
            vec![export::int_attr("keepdims", i64::from(keep))],
        ));
    }
}

/// The answer for `a → b` from its kernel `sums` (the arithmetic of the
/// graph, in the same order): training calls it once per setting on sums
/// it computed once per `σ`.
pub fn finish(
    settings: &Settings,
    sums: &Sums,
    a: [f32; 2],
    b: [f32; 2],
    prior: &[[f32; 2]],
) -> Prediction {
    let (mass, mass_sq) = (sums.mass, sums.mass_sq);
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let chord2 = dx * dx + dy * dy + TINY;
    let pi = settings.prior_weight;
    let total = mass + pi;
    let n_eff = total * total / (mass_sq + pi * pi);
    let used = if mass > settings.min_mass { 1.0 } else { 0.0 };
    let points = sums
        .points
        .iter()
        .zip(prior)
        .map(|(sum, z)| {
            let (rx, ry) = (z[0] - a[0], z[1] - a[1]);
            let (pr, pm) = ((rx * dx + ry * dy) / chord2, (ry * dx - rx * dy) / chord2);
            let re = (sum[0] + pr * pi) / total;
            let im = (sum[1] + pm * pi) / total;
            let sq = (sum[2] + (pr * pr + pm * pm) * pi) / total;
            let var = (sq - re * re - im * im).max(0.0);
            let (mr, mi) = (re - pr, im - pm);
            let mu2 = mr * mr + mi * mi;
            let lambda = mu2 / (mu2 + var * settings.shrink / n_eff + TINY) * used;
            let (fr, fi) = (pr + lambda * mr, pm + lambda * mi);
            [a[0] + (fr * dx - fi * dy), a[1] + (fr * dy + fi * dx)]
        })
        .collect();
    Prediction {
        points,
        learned: mass / total * used,
        mass,
    }
}

/// Keeps `λ` and the prior's shape defined where they would divide by 0.
const TINY: f32 = 1e-12;

#[cfg(test)]
mod tests {
    use super::*;

    fn straightish(bend: f32) -> [[f32; 2]; POINTS] {
        std::array::from_fn(|k| {
            let s = fraction(k);
            [s, bend * s * (1.0 - s)]
        })
    }

    fn straight(a: [f32; 2], b: [f32; 2]) -> Vec<[f32; 2]> {
        (0..POINTS)
            .map(|k| {
                let s = fraction(k);
                [a[0] + s * (b[0] - a[0]), a[1] + s * (b[1] - a[1])]
            })
            .collect()
    }

    #[test]
    fn agreeing_walks_bend_the_line_and_lone_or_far_ones_do_not() {
        let settings = Settings {
            sigma_cells: 2.0,
            shrink: 1.0,
            prior_weight: 1e-3,
            min_mass: 0.0,
        };
        let model = DesireLines {
            ends: vec![[0.5, 0.5, 10.5, 0.5]; 4],
            shapes: vec![straightish(0.4); 4],
            settings,
        };
        let (a, b) = ([0.5, 0.5], [10.5, 0.5]);
        let answer = model.predict(a, b, &straight(a, b));
        let line = &answer.points;
        assert_eq!(line.len(), POINTS);
        assert!((line[0][0] - 0.5).abs() < 1e-5 && (line[POINTS - 1][0] - 10.5).abs() < 1e-5);
        // Four walks that agree: the middle is 0.4 · ¼ · 10 = 1 cell off.
        assert!((line[POINTS / 2][1] - 1.5).abs() < 1e-3, "{line:?}");
        assert!(answer.learned > 0.99);
        // Far from every walk: the prior, and the model says the walks did
        // not answer once their mass is below τ.
        let (fa, fb) = ([30.5, 30.5], [40.5, 30.5]);
        let far = model.predict(fa, fb, &straight(fa, fb));
        assert!(
            far.points.iter().all(|p| (p[1] - 30.5).abs() < 1e-4),
            "{far:?}"
        );
        let gated = DesireLines {
            settings: Settings {
                min_mass: 0.5,
                ..settings
            },
            ..model.clone()
        };
        assert_eq!(gated.predict(fa, fb, &straight(fa, fb)).learned, 0.0);
        // A bent prior is kept where the walks do not speak: a heavy prior
        // weight holds the line to it even beside the walks.
        let bent: Vec<[f32; 2]> = straight(a, b)
            .into_iter()
            .enumerate()
            .map(|(k, p)| [p[0], p[1] - 2.0 * (fraction(k) * (1.0 - fraction(k)))])
            .collect();
        let heavy = DesireLines {
            settings: Settings {
                prior_weight: 1e6,
                ..settings
            },
            ..model.clone()
        };
        let held = heavy.predict(a, b, &bent);
        for (p, q) in held.points.iter().zip(&bent) {
            assert!((p[0] - q[0]).abs() < 1e-3 && (p[1] - q[1]).abs() < 1e-3);
        }
        // Walks that bend both ways: they cancel, and their spread keeps the
        // line straight.
        let split = DesireLines {
            shapes: vec![
                straightish(0.4),
                straightish(-0.4),
                straightish(0.4),
                straightish(-0.4),
            ],
            ..model
        };
        let line = split.predict(a, b, &straight(a, b)).points;
        assert!(line.iter().all(|p| (p[1] - 0.5).abs() < 1e-3), "{line:?}");
    }
}
