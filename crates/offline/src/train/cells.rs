//! The localization data set: survey readings as normalized features, labelled
//! with the index of their cell in `Site::open_cells`.
//!
//! Features use [`CellClassifierInput::normalize`], the same mapping the
//! exported graph applies to raw dBm. Rows are grouped into the surveyor's
//! sessions (a gap of more than [`SESSION_GAP_S`] between readings starts a
//! new one) so held-out rows come from walks the model never saw.

use ndarray::Array2;

use crate::locate::survey::Survey;
use crate::model::CellClassifierInput;
use crate::site::Site;

/// Readings further apart than this belong to different survey sessions.
pub(crate) const SESSION_GAP_S: f64 = 20.0;

pub(crate) struct CellSet {
    /// `[rows, anchors]` in [0, 1].
    pub features: Array2<f32>,
    /// Open-cell index per row.
    pub labels: Vec<usize>,
    /// Session per row (each row its own session when the survey has no times).
    pub sessions: Vec<usize>,
}

impl CellSet {
    pub(crate) fn from_survey(site: &Site, survey: &Survey) -> Result<CellSet, String> {
        let anchors = survey.anchors.len();
        let mut features = Array2::zeros((survey.samples.len(), anchors));
        let mut labels = Vec::with_capacity(survey.samples.len());
        let mut sessions = Vec::with_capacity(survey.samples.len());
        let mut session = 0;
        let mut last_t: Option<f64> = None;
        for (i, sample) in survey.samples.iter().enumerate() {
            let label = site.open_index(sample.cell).ok_or_else(|| {
                format!(
                    "survey row {} is at {}, which is not a walkable cell of the site",
                    i + 1,
                    sample.cell
                )
            })?;
            for (f, rssi) in features.row_mut(i).iter_mut().zip(&sample.rssi) {
                *f = rssi.map_or(0.0, |v| CellClassifierInput::normalize(f32::from(v)));
            }
            match (sample.t, last_t) {
                (Some(t), Some(prev)) if (t - prev).abs() <= SESSION_GAP_S => {}
                _ if i > 0 => session += 1,
                _ => {}
            }
            last_t = sample.t;
            labels.push(label);
            sessions.push(session);
        }
        Ok(CellSet {
            features,
            labels,
            sessions,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;
    use std::path::Path;

    #[test]
    fn sessions_break_on_time_gaps_and_features_are_normalized() {
        let site_text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n##\n'''\n\
            [[beacon]]\nid = \"b1\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\nmajor = 1\nminor = 1\n";
        let site = Site::parse(site_text, Path::new("t.toml")).unwrap();
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(b"x,y,t,b1\n0,0,0,-105\n1,0,5,-45\n1,0,100,-200\n")
            .unwrap();
        let survey = Survey::load(f.path(), &site, &["b1".into()], -200).unwrap();
        let set = CellSet::from_survey(&site, &survey).unwrap();
        assert_eq!(set.labels, vec![0, 1, 1]);
        assert_eq!(set.sessions, vec![0, 0, 1]);
        assert_eq!(set.features.column(0).to_vec(), vec![0.0, 1.0, 0.0]);
    }
}
