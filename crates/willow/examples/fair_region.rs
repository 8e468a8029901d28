//! Fair one region of a mesh file and write the result in the same format:
//!
//! ```sh
//! cargo run --release -p willow --example fair_region -- IN OUT X Y Z RADIUS [STEPS] [fixed|smooth]
//! ```
//!
//! Every vertex outside the sphere stays exactly where it was.

use willow::flow::region::{Region, Seam};
use willow::flow::{new_flow, FlowError, FlowParams};
use willow::mesh::io::{Asset, Format, Limits};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [input, output, x, y, z, radius, rest @ ..] = &args[..] else {
        return Err("usage: fair_region IN OUT X Y Z RADIUS [STEPS] [fixed|smooth]".into());
    };
    let format = |path: &str| -> Result<Format, Box<dyn std::error::Error>> {
        Format::from_path(std::path::Path::new(path))
            .ok_or_else(|| format!("{path}: unknown extension").into())
    };
    let asset = Asset::read(&std::fs::read(input)?, format(input)?, &Limits::default())?;
    let steps = rest.first().map_or(Ok(5), |s| s.parse())?;
    let seam = match rest.get(1).map(String::as_str) {
        Some("fixed") => Seam::Fixed,
        None | Some("smooth") => Seam::Smooth,
        Some(other) => return Err(format!("seam must be fixed or smooth, got {other}").into()),
    };
    let params = FlowParams {
        regions: vec![Region::Sphere {
            center: [x.parse()?, y.parse()?, z.parse()?],
            radius: radius.parse()?,
        }],
        seam,
        ..FlowParams::default()
    };
    let mut flow = new_flow(asset.surface(), &params)?;
    println!("step 0: W = {:.4}", flow.initial_metrics().willmore_energy);
    for _ in 0..steps {
        match flow.step() {
            Ok(m) => println!(
                "step {}: W = {:.4}, tau = {}, Q mean = {:.4}",
                m.step, m.willmore_energy, m.tau, m.q_mean
            ),
            Err(FlowError::NoProgress { step, .. }) => {
                println!("converged at step {step}");
                break;
            }
            Err(e) => return Err(e.into()),
        }
    }
    std::fs::write(output, asset.write(flow.positions(), format(output)?)?)?;
    Ok(())
}
