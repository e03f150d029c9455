//! A model package's super-resolution weights file (`MODEL.superres.npz`): what
//! `lp3d.lift.superres_weights` writes, `SuperresWeights::load` reads back exactly, and every
//! malformed file is refused with the file and key named.

use std::path::{Path, PathBuf};

use lp3d_renderer::npz::{write_npz, NpyArray, NpyData};
use lp3d_renderer::superres::{SuperresBlock, SuperresWeights, WEIGHTS_PARTS};

fn folder() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lp3d-superres-file-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Weights of a two-block network, 8 channels in, widths 6 and 4, distinct values throughout.
fn weights() -> SuperresWeights {
    let mut next = 0.0f32;
    let mut vec = |n: usize| {
        (0..n)
            .map(|_| {
                next += 0.001;
                next
            })
            .collect::<Vec<f32>>()
    };
    let mut cin = 8;
    let blocks = [6usize, 4]
        .iter()
        .map(|&c| {
            let b = SuperresBlock {
                channels: c,
                conv_up: vec(c * cin * 9),
                bias_up: vec(c),
                conv: vec(c * c * 9),
                bias: vec(c),
                rgb_weight: vec(3 * c),
                rgb_bias: vec(3),
            };
            cin = c;
            b
        })
        .collect();
    SuperresWeights { in_channels: 8, input_resolution: 16, blocks }
}

/// A weights file's arrays by key.
type Arrays = Vec<(String, NpyArray)>;

/// The file's arrays for `w`, as the Python writer names and shapes them.
fn arrays(w: &SuperresWeights) -> Arrays {
    let int = |v: i64| NpyArray { shape: vec![], data: NpyData::I64(vec![v]) };
    let mut out = vec![("format_version".to_string(), int(1)), ("input_resolution".into(), int(16))];
    let mut cin = w.in_channels;
    for (i, b) in w.blocks.iter().enumerate() {
        let c = b.channels;
        let parts: [(Vec<usize>, &Vec<f32>); 6] = [
            (vec![c, cin, 3, 3], &b.conv_up),
            (vec![c], &b.bias_up),
            (vec![c, c, 3, 3], &b.conv),
            (vec![c], &b.bias),
            (vec![3, c, 1, 1], &b.rgb_weight),
            (vec![3], &b.rgb_bias),
        ];
        for (name, (shape, values)) in WEIGHTS_PARTS.iter().zip(parts) {
            out.push((format!("{name}_{i}"), NpyArray::f32(shape, values.clone())));
        }
        cin = c;
    }
    out
}

fn write(path: &Path, arrays: &Arrays) {
    let named: Vec<(&str, NpyArray)> = arrays.iter().map(|(k, a)| (k.as_str(), a.clone())).collect();
    write_npz(std::fs::File::create(path).unwrap(), &named).unwrap();
}

#[test]
fn a_written_file_reads_back_exactly() {
    let path = folder().join("round-trip.npz");
    let w = weights();
    write(&path, &arrays(&w));
    assert_eq!(SuperresWeights::load(&path).unwrap(), w);
}

#[test]
fn malformed_files_name_the_file_and_key() {
    let dir = folder();
    let good = arrays(&weights());
    let refuse = |name: &str, edit: &dyn Fn(&mut Arrays)| -> String {
        let path = dir.join(name);
        let mut a = good.clone();
        edit(&mut a);
        write(&path, &a);
        let e = SuperresWeights::load(&path).expect_err("accepted").to_string();
        assert!(e.starts_with(&path.display().to_string()), "{e}");
        e
    };
    let set = |key: &'static str, value: NpyArray| {
        move |a: &mut Arrays| {
            a.iter_mut().find(|(k, _)| k == key).unwrap().1 = value.clone();
        }
    };
    let e = refuse(
        "version.npz",
        &set("format_version", NpyArray { shape: vec![], data: NpyData::I64(vec![2]) }),
    );
    assert!(e.contains("key 'format_version': 2 is not a version"), "{e}");
    let e = refuse("resolution.npz", &set("input_resolution", NpyArray::f32(vec![], vec![16.0])));
    assert!(e.contains("key 'input_resolution': must be an integer scalar"), "{e}");
    let e = refuse(
        "huge.npz",
        &set("input_resolution", NpyArray { shape: vec![], data: NpyData::I64(vec![1 << 40]) }),
    );
    assert!(e.contains("key 'input_resolution':"), "{e}");
    let e = refuse("flat.npz", &set("convs_1", NpyArray::f32(vec![4 * 4 * 9], vec![0.0; 4 * 4 * 9])));
    assert!(e.contains("key 'convs_1': shape must be [4, 4, 3, 3], got [144]"), "{e}");
    let e = refuse(
        "float64.npz",
        &set("biases_0", NpyArray { shape: vec![6], data: NpyData::F64(vec![0.0; 6]) }),
    );
    assert!(e.contains("key 'biases_0': must be float32, got float64"), "{e}");
    let e = refuse("missing.npz", &|a| a.retain(|(k, _)| k != "rgb_biases_1"));
    assert!(e.contains("expected format_version, input_resolution and the six arrays"), "{e}");
    let e = refuse("renamed.npz", &|a| {
        a.iter_mut().find(|(k, _)| k == "rgb_biases_1").unwrap().0 = "rgb_bias_1".into()
    });
    assert!(e.contains("key 'rgb_biases_1': missing"), "{e}");
    let mut nan = weights();
    nan.blocks[0].conv[3] = f32::NAN;
    let e = refuse("nan.npz", &|a| *a = arrays(&nan));
    assert!(e.contains("convs[0]: contains NaN/Inf at flat index 3"), "{e}");

    let e = SuperresWeights::load(&dir).unwrap_err().to_string();
    assert!(e.contains("is a directory, not a regular file (a super-resolution weights .npz)"), "{e}");
    let empty = dir.join("empty.npz");
    std::fs::write(&empty, b"").unwrap();
    assert!(SuperresWeights::load(&empty).unwrap_err().to_string().contains("0 bytes"));
}
