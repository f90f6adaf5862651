//! Desire lines: where people walk between two points, learned from their
//! walks, as a model any runtime can run.
//!
//! The model is a kernel regression over the training walks' shapes,
//! conditioned on the requested endpoints by their coordinates (cell units,
//! cell `(x, y)` spanning `[x, x+1) × [y, y+1)`), so it serves any pair of
//! points, on grids of any size: its input is 4 numbers, not a frame.
//!
//! Each training walk (in both directions) is stored as its end cells'
//! centres `(a_i, b_i)` and its shape `u_i(s)` at [`POINTS`] fractions `s` of
//! its length, as complex numbers normalised so the walk runs from 0 to 1:
//! `u_i(s) = (z_i(s) − z_i(0)) / (z_i(1) − z_i(0))`. A request `a → b`
//! weighs every walk by how near its ends are, `w_i = exp(−|x − e_i|² /
//! 2σ²)` over the four coordinates, and averages the shapes, `ū(s) = Σ w_i
//! u_i(s) / Σ w_i` (a walk's shape mapped onto the request's ends by the
//! similarity that takes its ends there, averaged). The average is then
//! shrunk towards the straight line `u = s`, point by point, by how much the
//! neighbours agree: with `μ = ū − s`, the spread `v` of their shapes around
//! `ū` and their effective number `n = (Σw)² / Σw²`,
//! `u = s + λ μ`, `λ = |μ|² / (|μ|² + c · v / n)`. Where few walks are near,
//! or they bend both ways, the line stays straight; where many agree, it
//! bends as they do. A small prior weight on the straight line keeps the
//! answer defined where no walk is near. `σ` and `c` are chosen by
//! cross-validation on the training walks (`train::desire`).
//!
//! The ONNX graph ([`DesireLines::to_onnx`]) computes exactly this with the
//! bank as constants: input `endpoints` `[N, 4]` (`ax, ay, bx, by`), output
//! `points` `[N, 2·P]` (the `P` x coordinates, then the `P` y coordinates, in
//! cell units, from `a` to `b`). [`DesireLines::predict`] is the same
//! arithmetic in Rust, which training uses to cross-validate.

use tract_onnx::pb;

use super::Metadata;
use super::export::{self, node};

/// Points per line, both ends included (16 segments).
pub const POINTS: usize = 17;

/// Weight of the straight line in every average: only matters where no walk
/// is near (weights underflow), where it makes the answer the straight line.
pub const PRIOR_WEIGHT: f32 = 1e-3;

/// The learned desire-line model: the walks' ends and shapes, and the two
/// settings cross-validation chose.
#[derive(Clone, Debug, PartialEq)]
pub struct DesireLines {
    /// `[ax, ay, bx, by]` per walk direction, cell units.
    pub ends: Vec<[f32; 4]>,
    /// The normalised shape per walk direction: (re, im) at each fraction.
    pub shapes: Vec<[[f32; 2]; POINTS]>,
    /// Kernel width σ over endpoint coordinates, cells.
    pub sigma_cells: f32,
    /// Shrinkage `c` towards the straight line.
    pub shrink: f32,
}

/// The fraction of the way along a line of point `k`.
pub fn fraction(k: usize) -> f32 {
    k as f32 / (POINTS - 1) as f32
}

impl DesireLines {
    /// The line from `a` to `b` (cell units), [`POINTS`] points, `a` first.
    pub fn predict(&self, a: [f32; 2], b: [f32; 2]) -> Vec<[f32; 2]> {
        let x = [a[0], a[1], b[0], b[1]];
        let scale = -1.0 / (2.0 * self.sigma_cells * self.sigma_cells);
        let mut total = PRIOR_WEIGHT;
        let mut total_sq = PRIOR_WEIGHT * PRIOR_WEIGHT;
        let mut re = [0f32; POINTS];
        let mut im = [0f32; POINTS];
        let mut sq = [0f32; POINTS];
        for (k, ((r, i), q)) in re.iter_mut().zip(&mut im).zip(&mut sq).enumerate() {
            let s = fraction(k);
            *r = PRIOR_WEIGHT * s;
            *i = 0.0;
            *q = PRIOR_WEIGHT * s * s;
        }
        for (e, shape) in self.ends.iter().zip(&self.shapes) {
            let d2: f32 = x.iter().zip(e).map(|(p, q)| (p - q) * (p - q)).sum();
            let w = (d2 * scale).exp();
            if w == 0.0 {
                continue;
            }
            total += w;
            total_sq += w * w;
            for (k, [ur, ui]) in shape.iter().enumerate() {
                re[k] += w * ur;
                im[k] += w * ui;
                sq[k] += w * (ur * ur + ui * ui);
            }
        }
        let n_eff = total * total / total_sq;
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        (0..POINTS)
            .map(|k| {
                let s = fraction(k);
                let (r, i) = (re[k] / total, im[k] / total);
                let var = (sq[k] / total - r * r - i * i).max(0.0);
                let (mr, mi) = (r - s, i);
                let m2 = mr * mr + mi * mi;
                let lambda = m2 / (m2 + self.shrink * var / n_eff + TINY);
                let (fr, fi) = (s + lambda * mr, lambda * mi);
                [a[0] + fr * dx - fi * dy, a[1] + fr * dy + fi * dx]
            })
            .collect()
    }

    /// The model as an ONNX graph (opset 13) with `meta` as its metadata.
    pub fn to_onnx(&self, meta: &Metadata) -> pb::ModelProto {
        let m = self.ends.len() as i64;
        let p = POINTS as i64;
        let mut init = Vec::new();
        let column = |f: &dyn Fn(usize) -> f32| -> Vec<f32> {
            (0..self.ends.len()).map(f).collect::<Vec<f32>>()
        };
        // Endpoints transposed [4, M] and their squared norms [1, M].
        let mut ends_t = Vec::with_capacity(4 * self.ends.len());
        for j in 0..4 {
            ends_t.extend(column(&|i| self.ends[i][j]));
        }
        init.push(export::tensor("bank.ends_t", &[4, m], &ends_t));
        let ends_sq = column(&|i| self.ends[i].iter().map(|v| v * v).sum());
        init.push(export::tensor("bank.ends_sq", &[1, m], &ends_sq));
        let plane = |f: &dyn Fn([f32; 2]) -> f32| -> Vec<f32> {
            self.shapes
                .iter()
                .flat_map(|shape| shape.iter().map(|&u| f(u)))
                .collect()
        };
        init.push(export::tensor("bank.u_re", &[m, p], &plane(&|u| u[0])));
        init.push(export::tensor("bank.u_im", &[m, p], &plane(&|u| u[1])));
        init.push(export::tensor(
            "bank.u_sq",
            &[m, p],
            &plane(&|u| u[0] * u[0] + u[1] * u[1]),
        ));
        let fractions: Vec<f32> = (0..POINTS).map(fraction).collect();
        init.push(export::tensor("fractions", &[1, p], &fractions));
        let prior_re: Vec<f32> = fractions.iter().map(|s| PRIOR_WEIGHT * s).collect();
        init.push(export::tensor("prior.re", &[1, p], &prior_re));
        let prior_sq: Vec<f32> = fractions.iter().map(|s| PRIOR_WEIGHT * s * s).collect();
        init.push(export::tensor("prior.sq", &[1, p], &prior_sq));
        let scalar = |name: &str, v: f32| export::tensor(name, &[], &[v]);
        init.push(scalar(
            "kernel.scale",
            -1.0 / (2.0 * self.sigma_cells * self.sigma_cells),
        ));
        init.push(scalar("shrink", self.shrink));
        init.push(scalar("prior", PRIOR_WEIGHT));
        init.push(scalar("prior.w2", PRIOR_WEIGHT * PRIOR_WEIGHT));
        init.push(scalar("two", 2.0));
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
        let mut nodes = Vec::new();
        let mut op = |op: &str, inputs: &[&str], out: &str| {
            nodes.push(node(
                op,
                inputs.iter().map(|s| s.to_string()).collect(),
                out,
                Vec::new(),
            ));
        };
        let x = "endpoints";
        // Squared distance of the request to every walk's ends, [N, M].
        op("Mul", &[x, x], "x.sq");
        op("ReduceSum", &["x.sq", "i1"], "x.norm");
        op("MatMul", &[x, "bank.ends_t"], "x.dot");
        op("Mul", &["x.dot", "two"], "x.dot2");
        op("Sub", &["x.norm", "x.dot2"], "d2.part");
        op("Add", &["d2.part", "bank.ends_sq"], "d2.raw");
        op("Relu", &["d2.raw"], "d2");
        op("Mul", &["d2", "kernel.scale"], "logw");
        op("Exp", &["logw"], "w");
        // Totals with the straight line's prior weight, [N, 1].
        op("ReduceSum", &["w", "i1"], "w.sum");
        op("Add", &["w.sum", "prior"], "total");
        op("Mul", &["w", "w"], "w.sq");
        op("ReduceSum", &["w.sq", "i1"], "w.sq.sum");
        op("Add", &["w.sq.sum", "prior.w2"], "total.sq");
        op("Mul", &["total", "total"], "total2");
        op("Div", &["total2", "total.sq"], "n_eff");
        // Weighted mean shape and its spread, [N, P].
        op("MatMul", &["w", "bank.u_re"], "re.part");
        op("Add", &["re.part", "prior.re"], "re.sum");
        op("Div", &["re.sum", "total"], "re");
        op("MatMul", &["w", "bank.u_im"], "im.sum");
        op("Div", &["im.sum", "total"], "im");
        op("MatMul", &["w", "bank.u_sq"], "sq.part");
        op("Add", &["sq.part", "prior.sq"], "sq.sum");
        op("Div", &["sq.sum", "total"], "sq");
        op("Mul", &["re", "re"], "re2");
        op("Mul", &["im", "im"], "im2");
        op("Sub", &["sq", "re2"], "var.part");
        op("Sub", &["var.part", "im2"], "var.raw");
        op("Relu", &["var.raw"], "var");
        // Shrunk towards the straight line.
        op("Sub", &["re", "fractions"], "mu.re");
        op("Mul", &["mu.re", "mu.re"], "mu.re2");
        op("Add", &["mu.re2", "im2"], "mu2");
        op("Mul", &["var", "shrink"], "var.c");
        op("Div", &["var.c", "n_eff"], "noise");
        op("Add", &["mu2", "noise"], "denominator.part");
        op("Add", &["denominator.part", "tiny"], "denominator");
        op("Div", &["mu2", "denominator"], "lambda");
        op("Mul", &["lambda", "mu.re"], "shift.re");
        op("Add", &["fractions", "shift.re"], "f.re");
        op("Mul", &["lambda", "im"], "f.im");
        // Onto the request's ends.
        for (k, name) in ["a.x", "a.y", "b.x", "b.y"].into_iter().enumerate() {
            let (start, end) = (format!("i{k}"), format!("i{}", k + 1));
            op("Slice", &[x, &start, &end, "i1"], name);
        }
        op("Sub", &["b.x", "a.x"], "d.x");
        op("Sub", &["b.y", "a.y"], "d.y");
        op("Mul", &["f.re", "d.x"], "rx");
        op("Mul", &["f.im", "d.y"], "iy");
        op("Sub", &["rx", "iy"], "px.rel");
        op("Add", &["a.x", "px.rel"], "points.x");
        op("Mul", &["f.re", "d.y"], "ry");
        op("Mul", &["f.im", "d.x"], "ix");
        op("Add", &["ry", "ix"], "py.rel");
        op("Add", &["a.y", "py.rel"], "points.y");
        nodes.push(node(
            "Concat",
            vec!["points.x".into(), "points.y".into()],
            "points",
            vec![export::int_attr("axis", 1)],
        ));
        // ReduceSum keeps its axis (the default keepdims = 1).
        export::model_proto(
            meta,
            nodes,
            init,
            vec![export::value_info(x, 4)],
            vec![export::value_info("points", 2 * POINTS)],
        )
    }
}

/// Keeps `λ` defined where the line is exactly straight.
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

    #[test]
    fn agreeing_walks_bend_the_line_and_lone_or_far_ones_do_not() {
        let model = DesireLines {
            ends: vec![[0.5, 0.5, 10.5, 0.5]; 4],
            shapes: vec![straightish(0.4); 4],
            sigma_cells: 2.0,
            shrink: 1.0,
        };
        let line = model.predict([0.5, 0.5], [10.5, 0.5]);
        assert_eq!(line.len(), POINTS);
        assert!((line[0][0] - 0.5).abs() < 1e-5 && (line[POINTS - 1][0] - 10.5).abs() < 1e-5);
        // Four walks that agree: the middle is 0.4 · ¼ · 10 = 1 cell off.
        assert!((line[POINTS / 2][1] - 1.5).abs() < 1e-3, "{line:?}");
        // Far from every walk: straight.
        let far = model.predict([30.5, 30.5], [40.5, 30.5]);
        assert!(far.iter().all(|p| (p[1] - 30.5).abs() < 1e-4), "{far:?}");
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
        let line = split.predict([0.5, 0.5], [10.5, 0.5]);
        assert!(line.iter().all(|p| (p[1] - 0.5).abs() < 1e-3), "{line:?}");
    }
}
