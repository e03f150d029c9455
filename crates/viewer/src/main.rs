//! `lp3d-view [--screenshot out.png] [--yaw D] [--pitch D] [--resolution R] [triplane.npz]`

fn main() {
    let options = match lp3d_viewer::ViewerOptions::from_args(std::env::args().skip(1)) {
        Ok(o) => o,
        Err(e) => {
            eprintln!("lp3d-view: {e}\n\n{}", lp3d_viewer::USAGE);
            std::process::exit(2);
        }
    };
    if options.help {
        println!("{}", lp3d_viewer::USAGE);
        return;
    }
    if let Err(e) = lp3d_viewer::run(options) {
        eprintln!("lp3d-view: {e}");
        std::process::exit(1);
    }
}
