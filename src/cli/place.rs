//! `doorslam place ...`: global place descriptors offline (describe, evaluate, vocabulary).

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use doorslam_ipc::wire::Descriptor;
use doorslam_place_recognition::bow::{
    default_vocabulary_path, keyframe_descriptors, orb_descriptors, Vocabulary, WIRE_DIM,
    WIRE_WHITENING,
};
use doorslam_place_recognition::describer::BOW_FEATURES;
use doorslam_place_recognition::eval::{
    at_threshold, pr_curve, svg, threshold_at_precision, EvalSet, Keyframe,
};
use doorslam_place_recognition::matching::{
    distance2, nearest, time_brute_force, wire_bytes_per_descriptor, Quantized,
};
use doorslam_place_recognition::netvlad::default_model_path;
use doorslam_place_recognition::{Describer, GrayImage, NetVlad};
use doorslam_rendezvous::chain_eval::{evaluate_chain, keyframe_features, ChainInput};

#[derive(Debug, Args)]
pub struct PlaceArgs {
    #[command(subcommand)]
    pub command: PlaceCommand,
}

#[derive(Debug, Subcommand)]
pub enum PlaceCommand {
    /// Descriptors of every keyframe of a KITTI / EuRoC folder or a `sim world` output.
    Describe(DescribeArgs),
    /// Precision-recall of inter-robot matches against ground truth.
    Eval(EvalArgs),
    /// Time brute-force matching: QUERIES x DATABASE random 128-D descriptors, float and int8.
    BenchMatch(BenchMatchArgs),
    /// Train the bag-of-words vocabulary (k-majority on ORB descriptors) on the left
    /// images of dataset folders, `sim world` outputs, folders of PNGs or PNG files.
    Vocabulary(VocabularyArgs),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MethodArg {
    Netvlad,
    Bow,
}

#[derive(Debug, Args)]
pub struct DescriberArgs {
    /// Which descriptor. The default is the one that wins on the held-out simulated
    /// flights (BENCHMARKS.md: today the bag of words; the rule).
    #[arg(long, value_enum, default_value = "bow")]
    pub method: MethodArg,
    /// NetVLAD ONNX model [default: $DOORSLAM_PLACE_MODEL, else
    /// $DOORSLAM_HOME/models/netvlad-effnetlite0-triplet-128.onnx].
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// BoW vocabulary [default: $DOORSLAM_BOW_VOCABULARY, else
    /// $DOORSLAM_HOME/models/bow-orb-1024-w128.voc].
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
    /// onnxruntime intra-op threads (1 = the one-core figure).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Every N-th frame is a keyframe.
    #[arg(long, default_value_t = 1)]
    pub stride: usize,
    /// Bag of words: ORB's own detector on the left image (what the vocabulary trains on)
    /// or the front-end's keyframe features (GFTT + upright ORB with a stereo match: what
    /// `Keyframe` samples carry; needs the right images).
    #[arg(long, value_enum, default_value = "orb")]
    pub features: FeaturesArg,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FeaturesArg {
    Orb,
    Frontend,
}

#[derive(Debug, Args)]
pub struct DescribeArgs {
    pub dir: PathBuf,
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub describer: DescriberArgs,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct EvalArgs {
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    #[command(flatten)]
    pub describer: DescriberArgs,
    /// Match on the int8 wire form (integer dot products) instead of float.
    #[arg(long)]
    pub int8: bool,
    /// Match on the 128-D wire form in float (bag of words: its PCA projection; NetVLAD:
    /// its first 128 values), without the int8 rounding.
    #[arg(long, conflicts_with = "int8")]
    pub projected: bool,
    /// Also print (stderr) precision and recall at this match threshold [default with
    /// --int8: the method's default threshold, the one the service uses].
    #[arg(long)]
    pub threshold: Option<f64>,
    /// Where to write the precision-recall curve [default: pr_<method>[_int8].svg].
    #[arg(long)]
    pub svg: Option<PathBuf>,
    /// Also run the whole candidate chain on the wire form (implies --int8): top-k below
    /// the distance bound (--threshold, default the method's), temporal confirmation, PnP
    /// verification on the front-end's keyframe features; adds `verified_recall`,
    /// `verified_false`, `verified_aliased`, `verification_requests`,
    /// `bytes_per_true_closure` and the counts of every stage (`chain`).
    #[arg(long, conflicts_with = "projected")]
    pub verify: bool,
    /// Candidates per query [default: the method's chain, `Method::default_chain`].
    #[arg(long, requires = "verify")]
    pub top_k: Option<usize>,
    /// Temporal neighbours looked at, in keyframes on each side.
    #[arg(long, requires = "verify")]
    pub temporal_window: Option<u64>,
    /// Neighbours that must agree (0: no temporal check).
    #[arg(long, requires = "verify")]
    pub min_support: Option<usize>,
    /// A neighbour agrees when one of its candidates is within this many keyframes of the
    /// pair's candidate.
    #[arg(long, requires = "verify")]
    pub max_gap: Option<u64>,
    /// Verification settings (TOML with any fields of the front-end's VerifyConfig, as
    /// `[rendezvous.verify]` of robot.toml).
    #[arg(long, requires = "verify")]
    pub verify_config: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct BenchMatchArgs {
    #[arg(long, default_value_t = 1000)]
    pub queries: usize,
    #[arg(long, default_value_t = 10000)]
    pub database: usize,
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, Args)]
pub struct VocabularyArgs {
    #[arg(required = true)]
    pub dirs: Vec<PathBuf>,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 1024)]
    pub words: usize,
    #[arg(long, default_value_t = 10)]
    pub iterations: usize,
    /// Every N-th frame trains.
    #[arg(long, default_value_t = 2)]
    pub stride: usize,
    /// Whitening power of the 128-D wire projection fitted on the same images (0: plain
    /// PCA, 1: full whitening).
    #[arg(long, default_value_t = WIRE_WHITENING)]
    pub whiten: f64,
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: PlaceArgs) -> Result<()> {
    match args.command {
        PlaceCommand::Describe(a) => describe(a),
        PlaceCommand::Eval(a) => eval(a),
        PlaceCommand::Vocabulary(a) => vocabulary(a),
        PlaceCommand::BenchMatch(a) => bench_match(a),
    }
}

fn bench_match(a: BenchMatchArgs) -> Result<()> {
    let (float_s, int8_s, agree) = time_brute_force(a.queries, a.database);
    let json = serde_json::json!({
        "queries": a.queries,
        "database": a.database,
        "float_s": float_s,
        "int8_s": int8_s,
        "nearest_agree": agree,
    });
    if a.json {
        println!("{json}");
    } else {
        println!(
            "{} x {} brute force: float {float_s:.3} s, int8 {int8_s:.3} s, {agree} nearest neighbours agree",
            a.queries, a.database
        );
    }
    Ok(())
}

fn open_describer(a: &DescriberArgs) -> Result<Describer> {
    Ok(match a.method {
        MethodArg::Netvlad => {
            let path = a.model.clone().unwrap_or_else(default_model_path);
            Describer::NetVlad(NetVlad::from_file(&path, a.threads)?)
        }
        MethodArg::Bow => {
            let path = a.vocabulary.clone().unwrap_or_else(default_vocabulary_path);
            Describer::BagOfWords(Vocabulary::from_file(&path)?)
        }
    })
}

fn load_image(path: &Path) -> Result<GrayImage> {
    let (w, h, pixels) = doorslam_dataset::read_gray_png(path)?;
    GrayImage::new(w as usize, h as usize, pixels)
        .with_context(|| format!("{}: empty image", path.display()))
}

/// Descriptors of all keyframes in batches of 8 (with `wire`: their 128-D wire form), and
/// the describe time per image (preprocessing included, PNG decoding excluded).
fn describe_all(
    describer: &mut Describer,
    keyframes: &[Keyframe],
    features: FeaturesArg,
    wire: bool,
) -> Result<(Vec<Vec<f32>>, f64)> {
    let mut out = Vec::with_capacity(keyframes.len());
    let mut seconds = 0.0;
    // One untimed run first: onnxruntime allocates its buffers on the first inference.
    if let Some(first) = keyframes.first() {
        describer.describe(&[load_image(&first.image)?])?;
    }
    let mut extractor = match (features, &*describer) {
        (FeaturesArg::Orb, _) => None,
        (FeaturesArg::Frontend, Describer::BagOfWords(_)) => Some(doorslam_vision::Extractor::new(
            &doorslam_frontend::VoConfig::default().features(),
        )?),
        (FeaturesArg::Frontend, Describer::NetVlad(_)) => {
            bail!("--features frontend is for the bag of words (NetVLAD describes images)")
        }
    };
    for (i, chunk) in keyframes.chunks(8).enumerate() {
        let images = chunk
            .iter()
            .map(|k| load_image(&k.image))
            .collect::<Result<Vec<_>>>()?;
        let rights = match extractor {
            Some(_) => chunk
                .iter()
                .map(|k| {
                    let right = k.right.as_ref().with_context(|| {
                        format!(
                            "{}: no right image for --features frontend",
                            k.image.display()
                        )
                    })?;
                    load_image(right)
                })
                .collect::<Result<Vec<_>>>()?,
            None => Vec::new(),
        };
        let start = Instant::now();
        let described = match (&mut extractor, &mut *describer) {
            (Some(x), Describer::BagOfWords(voc)) => images
                .iter()
                .zip(&rights)
                .map(|(l, r)| Ok(voc.describe(&keyframe_descriptors(x, l, r)?)))
                .collect::<Result<Vec<_>>>()?,
            (_, d) => d.describe(&images)?,
        };
        if wire {
            for d in &described {
                out.push(describer.to_wire(d)?);
            }
        } else {
            out.extend(described);
        }
        seconds += start.elapsed().as_secs_f64();
        if i % 25 == 24 {
            eprintln!(
                "place: {}/{} keyframes described",
                out.len(),
                keyframes.len()
            );
        }
    }
    Ok((out, 1e3 * seconds / keyframes.len().max(1) as f64))
}

fn describe(a: DescribeArgs) -> Result<()> {
    let set = EvalSet::load(std::slice::from_ref(&a.dir), a.describer.stride)
        .or_else(|_| keyframes_without_truth(&a.dir, a.describer.stride))
        .with_context(|| format!("reading {}", a.dir.display()))?;
    let mut describer = open_describer(&a.describer)?;
    let (descriptors, ms) =
        describe_all(&mut describer, &set.keyframes, a.describer.features, false)?;
    let mut text = format!(
        "# doorslam place descriptors: method={} dim={}\n# robot frame values...\n",
        describer.method().name(),
        describer.dim()
    );
    for (k, d) in set.keyframes.iter().zip(&descriptors) {
        let values: Vec<String> = d.iter().map(|v| format!("{v:.6}")).collect();
        text += &format!("{} {} {}\n", k.robot, k.frame, values.join(" "));
    }
    std::fs::write(&a.out, text).with_context(|| format!("writing {}", a.out.display()))?;
    let json = serde_json::json!({
        "out": a.out.display().to_string(),
        "method": describer.method().name(),
        "keyframes": descriptors.len(),
        "dim": describer.dim(),
        "ms_per_descriptor": ms,
    });
    if a.json {
        println!("{json}");
    } else {
        println!(
            "{}: {} {} descriptors of dim {}, {ms:.1} ms each",
            a.out.display(),
            descriptors.len(),
            describer.method().name(),
            describer.dim()
        );
    }
    Ok(())
}

/// A folder without ground truth still has descriptors (KITTI raw, EuRoC).
fn keyframes_without_truth(dir: &Path, stride: usize) -> Result<EvalSet> {
    let data = doorslam_dataset::Dataset::open(dir)?;
    let keyframes = data
        .frames
        .iter()
        .step_by(stride.max(1))
        .map(|f| Keyframe {
            robot: "0".into(),
            frame: f.index,
            image: f.left.clone(),
            right: Some(f.right.clone()),
            pose: nalgebra::Isometry3::identity(),
        })
        .collect();
    Ok(EvalSet {
        keyframes,
        ..Default::default()
    })
}

fn eval(mut a: EvalArgs) -> Result<()> {
    a.int8 |= a.verify;
    let set = EvalSet::load(&a.dirs, a.describer.stride)?;
    let mut describer = open_describer(&a.describer)?;
    if let Describer::NetVlad(m) = &describer {
        let trained = set.training_towns(m.training_towns());
        if let Some((dir, seed)) = trained.first() {
            bail!(
                "{}: town seed {seed} is one the model was trained on (its metadata lists {:?}); \
                 evaluate on towns it never saw",
                dir.display(),
                m.training_towns()
            );
        }
    }
    let method = describer.method().name();
    let wire = a.int8 || a.projected;
    eprintln!(
        "place eval: {} keyframes, {} true inter-robot pairs",
        set.keyframes.len(),
        set.positives.len() / 2
    );
    let (descriptors, ms) =
        describe_all(&mut describer, &set.keyframes, a.describer.features, wire)?;
    let allowed = |q: usize, d: usize| set.inter_robot(q, d);
    let (nn, bytes) = if a.int8 {
        let quantized = descriptors
            .iter()
            .enumerate()
            .map(|(i, d)| Ok(Quantized::new(Descriptor::quantize(i as u64, d)?)))
            .collect::<Result<Vec<_>>>()?;
        let nn = nearest(&quantized, &quantized, |x, y| x.distance2(y), allowed);
        // What α sends at a first rendezvous: all its keyframes in one batch.
        let robots: std::collections::HashSet<&str> =
            set.keyframes.iter().map(|k| k.robot.as_str()).collect();
        let batch = set.keyframes.len() / robots.len().max(1);
        (nn, wire_bytes_per_descriptor(batch))
    } else {
        let nn = nearest(&descriptors, &descriptors, |x, y| distance2(x, y), allowed);
        // Float: 4 bytes per value (BoW: the non-zero entries, u16 word + f32 weight).
        let bytes = match describer {
            _ if a.projected => 4.0 * WIRE_DIM as f64,
            Describer::NetVlad(_) => 4.0 * describer.dim() as f64,
            Describer::BagOfWords(_) => {
                let nonzero: usize = descriptors
                    .iter()
                    .map(|d| d.iter().filter(|v| **v != 0.0).count())
                    .sum();
                6.0 * nonzero as f64 / descriptors.len().max(1) as f64
            }
        };
        (nn, bytes)
    };
    let curve = pr_curve(&set, &nn);
    let form = match (a.int8, a.projected) {
        (true, _) => "_int8",
        (_, true) => "_projected",
        _ => "",
    };
    let features = match a.describer.features {
        FeaturesArg::Frontend => "_frontend",
        FeaturesArg::Orb => "",
    };
    let label = format!("{method}{form}{features}").replace('_', " ");
    let svg_path = a
        .svg
        .clone()
        .unwrap_or_else(|| PathBuf::from(format!("pr_{method}{form}{features}.svg")));
    std::fs::write(&svg_path, svg(&[(&label, &curve)]))
        .with_context(|| format!("writing {}", svg_path.display()))?;
    eprintln!(
        "place eval: PR curve in {}; {} queries have a true match",
        svg_path.display(),
        curve.queries_with_positive
    );
    // The match threshold from this descriptor's own curve (BENCHMARKS.md: the defaults).
    for precision in [0.8, 0.9, 0.95] {
        match threshold_at_precision(&curve, precision) {
            Some((t, recall)) => eprintln!(
                "place eval: threshold for precision >= {precision}: {t:.4} (recall {recall:.3})"
            ),
            None => eprintln!("place eval: no threshold reaches precision {precision}"),
        }
    }
    let threshold = a.threshold.or(a
        .int8
        .then(|| f64::from(describer.method().default_threshold())));
    if let Some(t) = threshold {
        match at_threshold(&curve, t) {
            Some((recall, precision)) => eprintln!(
                "place eval: at threshold {t:.4}: precision {precision:.3}, recall {recall:.3}"
            ),
            None => eprintln!("place eval: threshold {t:.4} accepts no match"),
        }
    }
    let mut json = serde_json::json!({
        "method": method,
        "queries": curve.queries,
        "recall_at_1": curve.recall_at_1,
        "precision_at_recall_0_5": curve.precision_at_recall_0_5,
        "auc": curve.auc,
        "bytes_per_descriptor": bytes,
        "ms_per_descriptor": ms,
    });
    if a.verify {
        let chain = verify_chain(&a, &set, &descriptors, describer.method(), threshold)?;
        if let serde_json::Value::Object(o) = &mut json {
            o.extend(chain.as_object().cloned().unwrap_or_default());
        }
    }
    if a.json {
        println!("{json}");
    } else {
        println!(
            "{label}: {} queries, recall@1 {:.3}, precision at recall 0.5 {:.3}, AUC {:.3}, {bytes:.0} B/descriptor, {ms:.1} ms/descriptor",
            curve.queries, curve.recall_at_1, curve.precision_at_recall_0_5, curve.auc
        );
        if a.verify {
            println!(
                "chain: {} verification requests, verified recall {:.3}, {} false ({} aliased), {} B per true closure",
                json["verification_requests"],
                json["verified_recall"].as_f64().unwrap_or(0.0),
                json["verified_false"],
                json["verified_aliased"],
                json["bytes_per_true_closure"]
            );
        }
    }
    std::io::stdout().flush()?;
    Ok(())
}

/// `--verify`: the candidate chain and PnP verification over the set (library:
/// `chain_eval`), as the JSON fields it adds.
fn verify_chain(
    a: &EvalArgs,
    set: &EvalSet,
    descriptors: &[Vec<f32>],
    method: doorslam_place_recognition::Method,
    threshold: Option<f64>,
) -> Result<serde_json::Value> {
    let mut chain = method.default_chain();
    if let Some(t) = threshold {
        chain.max_distance = t as f32;
    }
    chain.top_k = a.top_k.unwrap_or(chain.top_k);
    chain.window = a.temporal_window.unwrap_or(chain.window);
    chain.min_support = a.min_support.unwrap_or(chain.min_support);
    chain.max_gap = a.max_gap.unwrap_or(chain.max_gap);
    chain
        .validate()
        .map_err(|e| anyhow::anyhow!("--verify: {e}"))?;
    let verify_config: doorslam_frontend::VerifyConfig = match &a.verify_config {
        Some(p) => toml::from_str(
            &std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?,
        )
        .with_context(|| format!("{}: not a verification config", p.display()))?,
        None => Default::default(),
    };
    eprintln!("place eval --verify: the front-end's features of every keyframe");
    let progress = |done: usize, total: usize| {
        if done.is_multiple_of(250) || done == total {
            eprintln!("place eval --verify: {done}/{total} keyframes");
        }
    };
    let (features, calibration, features_ms) =
        keyframe_features(set, &doorslam_frontend::VoConfig::default(), &progress)?;
    let input = ChainInput {
        set,
        descriptors,
        features: &features,
        calibration: &calibration,
    };
    let report = evaluate_chain(
        &input,
        &chain,
        &verify_config,
        doorslam_frontend::MAX_PACKET_FEATURES,
    )
    .map_err(|e| anyhow::anyhow!("--verify: {e}"))?;
    Ok(serde_json::json!({
        "verified_recall": report.verified_recall,
        "verified_false": report.verified_false,
        "verified_aliased": report.verified_aliased,
        "verification_requests": report.verification_requests,
        "bytes_per_true_closure": report.bytes_per_true_closure,
        "verified_false_near": report.verified_false_near,
        "verified_false_far": report.verified_false_far,
        "accepted": report.accepted,
        "accepted_false": report.accepted_false,
        "accepted_aliased": report.accepted_aliased,
        "accepted_recall": report.accepted_recall,
        "chain": {
            "config": chain,
            "stages": report.chain,
            "packets": report.packets,
            "verified": report.verified,
            "verified_true": report.verified_true,
            "rejected": report.rejected,
            "true_overlaps": report.true_overlaps,
            "true_overlaps_found": report.true_overlaps_found,
            "bytes": report.bytes,
            "worst_true_error_m": report.worst_true_error_m,
            "worst_true_error_deg": report.worst_true_error_deg,
            "ms_per_verification": report.ms_per_verification,
            "ms_per_keyframe_features": features_ms,
        },
    }))
}

fn vocabulary(a: VocabularyArgs) -> Result<()> {
    let start = Instant::now();
    let mut images = Vec::new();
    for dir in &a.dirs {
        let set = if dir.is_file() {
            single_image(dir)
        } else {
            keyframes_of_any(dir, a.stride)?
        };
        for k in &set.keyframes {
            images.push(orb_descriptors(&load_image(&k.image)?, BOW_FEATURES)?);
        }
        if dir.is_dir() {
            eprintln!(
                "place vocabulary: {} ({} images so far)",
                dir.display(),
                images.len()
            );
        }
    }
    let mut voc = Vocabulary::train(&images, a.words, a.iterations, 1).with_context(|| {
        format!(
            "{} training images have fewer than {} ORB features",
            images.len(),
            a.words
        )
    })?;
    // The wire form: PCA of the same images' TF-IDF vectors to 128-D.
    voc.fit_projection(&images, WIRE_DIM.min(a.words), a.whiten)
        .context("fitting the 128-D wire projection")?;
    if let Some(parent) = a.out.parent() {
        std::fs::create_dir_all(parent)?;
    }
    std::fs::write(&a.out, voc.to_bytes())
        .with_context(|| format!("writing {}", a.out.display()))?;
    let json = serde_json::json!({
        "out": a.out.display().to_string(),
        "words": a.words,
        "images": images.len(),
        "features": images.iter().map(Vec::len).sum::<usize>(),
        "wire_dim": WIRE_DIM.min(a.words),
        "whiten": a.whiten,
        "seconds": start.elapsed().as_secs_f64(),
    });
    if a.json {
        println!("{json}");
    } else {
        println!(
            "{}: {} words from {} images",
            a.out.display(),
            a.words,
            images.len()
        );
    }
    Ok(())
}

fn single_image(path: &Path) -> EvalSet {
    EvalSet {
        keyframes: vec![Keyframe {
            robot: "0".into(),
            frame: 0,
            image: path.to_path_buf(),
            right: None,
            pose: nalgebra::Isometry3::identity(),
        }],
        ..Default::default()
    }
}

/// Keyframes of a folder with or without ground truth, or of a plain folder of PNGs.
fn keyframes_of_any(dir: &Path, stride: usize) -> Result<EvalSet> {
    if let Ok(set) = EvalSet::load(&[dir.to_path_buf()], stride) {
        return Ok(set);
    }
    if let Ok(set) = keyframes_without_truth(dir, stride) {
        return Ok(set);
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    files.sort();
    if files.is_empty() {
        bail!("{}: no dataset and no PNG images", dir.display());
    }
    Ok(EvalSet {
        keyframes: files
            .into_iter()
            .step_by(stride.max(1))
            .enumerate()
            .map(|(i, image)| Keyframe {
                robot: "0".into(),
                frame: i,
                image,
                right: None,
                pose: nalgebra::Isometry3::identity(),
            })
            .collect(),
        ..Default::default()
    })
}
