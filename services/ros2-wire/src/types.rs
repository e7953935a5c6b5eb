//! ROS 2 message definitions as data: what the RIHS01 type hash, the `ros2msg` schema
//! text of a bag and the DDS type name are computed from. The definitions are Jazzy's
//! (Humble's `Marker` lacks `texture`, `uv_coordinates` and `mesh_file`, so its hash
//! differs; Jazzy's and Kilted's agree).
//!
//! The type hash (REP-2011, "RIHS01_" + SHA-256 hex) is taken over a JSON form of the
//! type description: `{"type_description": T, "referenced_type_descriptions": [R...]}`,
//! each description `{"type_name": "pkg/msg/Name", "fields": [{"name": .., "type":
//! {"type_id": .., "capacity": .., "string_capacity": .., "nested_type_name": ..}}]}`,
//! the referenced types every nested type reached, sorted by name, constants and default
//! values left out, written with `", "` and `": "` between items (Python's `json.dumps`
//! defaults, which rosidl uses).

use std::collections::BTreeMap;
use std::fmt::Write as _;

use sha2::{Digest, Sha256};

/// A primitive field type (the ones these messages use).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prim {
    Bool,
    /// `byte`: an octet.
    Byte,
    U8,
    I32,
    U32,
    F32,
    F64,
    String,
}

impl Prim {
    /// The .msg spelling.
    pub fn msg_name(self) -> &'static str {
        match self {
            Prim::Bool => "bool",
            Prim::Byte => "byte",
            Prim::U8 => "uint8",
            Prim::I32 => "int32",
            Prim::U32 => "uint32",
            Prim::F32 => "float32",
            Prim::F64 => "float64",
            Prim::String => "string",
        }
    }

    /// `type_description_interfaces/msg/FieldType` ids.
    fn type_id(self) -> u8 {
        match self {
            Prim::U8 => 3,
            Prim::I32 => 6,
            Prim::U32 => 7,
            Prim::F32 => 10,
            Prim::F64 => 11,
            Prim::Bool => 15,
            Prim::Byte => 16,
            Prim::String => 17,
        }
    }
}

/// What a field holds.
#[derive(Debug, Clone, Copy)]
pub enum Elem {
    Prim(Prim),
    Msg(&'static TypeDef),
}

/// One field: a value or an unbounded sequence of them.
#[derive(Debug, Clone, Copy)]
pub struct FieldDef {
    pub name: &'static str,
    pub elem: Elem,
    pub sequence: bool,
}

/// A constant of the .msg (in the schema text, not in the hash).
#[derive(Debug, Clone, Copy)]
pub struct ConstDef {
    pub ty: Prim,
    pub name: &'static str,
    pub value: &'static str,
}

/// One message type.
#[derive(Debug)]
pub struct TypeDef {
    /// `pkg/msg/Name`.
    pub name: &'static str,
    pub constants: &'static [ConstDef],
    pub fields: &'static [FieldDef],
}

/// Offsets of `FieldType` ids for sequences: unbounded 144 (arrays 48, bounded 96).
const UNBOUNDED_SEQUENCE: u8 = 144;
/// `FieldType.FIELD_TYPE_NESTED_TYPE`.
const NESTED: u8 = 1;

impl TypeDef {
    /// `pkg/Name`, how .msg files and bag schemas name a type.
    pub fn short_name(&self) -> String {
        self.name.replacen("/msg/", "/", 1)
    }

    /// The DDS type name rmw implementations use for CDR: `pkg::msg::dds_::Name_`.
    pub fn dds_name(&self) -> String {
        let mut parts = self.name.split('/');
        let (pkg, kind, name) = (
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
            parts.next().unwrap_or_default(),
        );
        format!("{pkg}::{kind}::dds_::{name}_")
    }

    /// Every nested type reached from this one (itself excluded), by name.
    fn referenced(&'static self) -> BTreeMap<&'static str, &'static TypeDef> {
        let mut out = BTreeMap::new();
        let mut stack = vec![self];
        while let Some(t) = stack.pop() {
            for f in t.fields {
                if let Elem::Msg(m) = f.elem {
                    if m.name != self.name && out.insert(m.name, m).is_none() {
                        stack.push(m);
                    }
                }
            }
        }
        out
    }

    fn description_json(&self, out: &mut String) {
        let _ = write!(out, "{{\"type_name\": \"{}\", \"fields\": [", self.name);
        for (i, f) in self.fields.iter().enumerate() {
            if i > 0 {
                out.push_str(", ");
            }
            let (base, nested) = match f.elem {
                Elem::Prim(p) => (p.type_id(), ""),
                Elem::Msg(m) => (NESTED, m.name),
            };
            let id = if f.sequence {
                base + UNBOUNDED_SEQUENCE
            } else {
                base
            };
            let _ = write!(
                out,
                "{{\"name\": \"{}\", \"type\": {{\"type_id\": {id}, \"capacity\": 0, \
                 \"string_capacity\": 0, \"nested_type_name\": \"{nested}\"}}}}",
                f.name
            );
        }
        out.push_str("]}");
    }

    /// The JSON the type hash is taken over.
    pub fn hash_json(&'static self) -> String {
        let mut out = String::from("{\"type_description\": ");
        self.description_json(&mut out);
        out.push_str(", \"referenced_type_descriptions\": [");
        for (i, t) in self.referenced().values().enumerate() {
            if i > 0 {
                out.push_str(", ");
            }
            t.description_json(&mut out);
        }
        out.push_str("]}");
        out
    }

    /// `RIHS01_<sha256 hex>`, as rosidl computes it.
    pub fn type_hash(&'static self) -> String {
        let digest = Sha256::digest(self.hash_json().as_bytes());
        let mut out = String::from("RIHS01_");
        for b in digest {
            let _ = write!(out, "{b:02x}");
        }
        out
    }

    /// This type's own .msg text: constants, then fields, one a line.
    pub fn msg_text(&self) -> String {
        let mut out = String::new();
        for c in self.constants {
            let _ = writeln!(out, "{} {}={}", c.ty.msg_name(), c.name, c.value);
        }
        for f in self.fields {
            let ty = match f.elem {
                Elem::Prim(p) => p.msg_name().to_string(),
                Elem::Msg(m) => m.short_name(),
            };
            let _ = writeln!(out, "{ty}{} {}", if f.sequence { "[]" } else { "" }, f.name);
        }
        out
    }

    /// The `ros2msg` schema of a bag: this type's text, then every type it uses (depth
    /// first, in field order, each once) after a line of 80 `=` and `MSG: pkg/Name`, the
    /// way `ros2 bag record` concatenates them.
    pub fn schema_text(&'static self) -> String {
        fn visit(t: &'static TypeDef, seen: &mut Vec<&'static str>, out: &mut String) {
            for f in t.fields {
                if let Elem::Msg(m) = f.elem {
                    if !seen.contains(&m.name) {
                        seen.push(m.name);
                        let _ = write!(
                            out,
                            "{}\nMSG: {}\n{}",
                            "=".repeat(80),
                            m.short_name(),
                            m.msg_text()
                        );
                        visit(m, seen, out);
                    }
                }
            }
        }
        let mut out = self.msg_text();
        let mut seen = vec![self.name];
        visit(self, &mut seen, &mut out);
        out
    }
}

const fn value(name: &'static str, p: Prim) -> FieldDef {
    FieldDef {
        name,
        elem: Elem::Prim(p),
        sequence: false,
    }
}

const fn nested(name: &'static str, t: &'static TypeDef) -> FieldDef {
    FieldDef {
        name,
        elem: Elem::Msg(t),
        sequence: false,
    }
}

const fn nested_seq(name: &'static str, t: &'static TypeDef) -> FieldDef {
    FieldDef {
        name,
        elem: Elem::Msg(t),
        sequence: true,
    }
}

const fn prim_seq(name: &'static str, p: Prim) -> FieldDef {
    FieldDef {
        name,
        elem: Elem::Prim(p),
        sequence: true,
    }
}

const fn konst(ty: Prim, name: &'static str, value: &'static str) -> ConstDef {
    ConstDef { ty, name, value }
}

pub static TIME: TypeDef = TypeDef {
    name: "builtin_interfaces/msg/Time",
    constants: &[],
    fields: &[value("sec", Prim::I32), value("nanosec", Prim::U32)],
};

pub static DURATION: TypeDef = TypeDef {
    name: "builtin_interfaces/msg/Duration",
    constants: &[],
    fields: &[value("sec", Prim::I32), value("nanosec", Prim::U32)],
};

pub static HEADER: TypeDef = TypeDef {
    name: "std_msgs/msg/Header",
    constants: &[],
    fields: &[nested("stamp", &TIME), value("frame_id", Prim::String)],
};

pub static COLOR_RGBA: TypeDef = TypeDef {
    name: "std_msgs/msg/ColorRGBA",
    constants: &[],
    fields: &[
        value("r", Prim::F32),
        value("g", Prim::F32),
        value("b", Prim::F32),
        value("a", Prim::F32),
    ],
};

pub static POINT: TypeDef = TypeDef {
    name: "geometry_msgs/msg/Point",
    constants: &[],
    fields: &[
        value("x", Prim::F64),
        value("y", Prim::F64),
        value("z", Prim::F64),
    ],
};

pub static VECTOR3: TypeDef = TypeDef {
    name: "geometry_msgs/msg/Vector3",
    constants: &[],
    fields: &[
        value("x", Prim::F64),
        value("y", Prim::F64),
        value("z", Prim::F64),
    ],
};

pub static QUATERNION: TypeDef = TypeDef {
    name: "geometry_msgs/msg/Quaternion",
    constants: &[],
    fields: &[
        value("x", Prim::F64),
        value("y", Prim::F64),
        value("z", Prim::F64),
        value("w", Prim::F64),
    ],
};

pub static POSE: TypeDef = TypeDef {
    name: "geometry_msgs/msg/Pose",
    constants: &[],
    fields: &[
        nested("position", &POINT),
        nested("orientation", &QUATERNION),
    ],
};

pub static POSE_STAMPED: TypeDef = TypeDef {
    name: "geometry_msgs/msg/PoseStamped",
    constants: &[],
    fields: &[nested("header", &HEADER), nested("pose", &POSE)],
};

pub static TRANSFORM: TypeDef = TypeDef {
    name: "geometry_msgs/msg/Transform",
    constants: &[],
    fields: &[
        nested("translation", &VECTOR3),
        nested("rotation", &QUATERNION),
    ],
};

pub static TRANSFORM_STAMPED: TypeDef = TypeDef {
    name: "geometry_msgs/msg/TransformStamped",
    constants: &[],
    fields: &[
        nested("header", &HEADER),
        value("child_frame_id", Prim::String),
        nested("transform", &TRANSFORM),
    ],
};

pub static PATH: TypeDef = TypeDef {
    name: "nav_msgs/msg/Path",
    constants: &[],
    fields: &[
        nested("header", &HEADER),
        nested_seq("poses", &POSE_STAMPED),
    ],
};

pub static TF_MESSAGE: TypeDef = TypeDef {
    name: "tf2_msgs/msg/TFMessage",
    constants: &[],
    fields: &[nested_seq("transforms", &TRANSFORM_STAMPED)],
};

pub static COMPRESSED_IMAGE: TypeDef = TypeDef {
    name: "sensor_msgs/msg/CompressedImage",
    constants: &[],
    fields: &[
        nested("header", &HEADER),
        value("format", Prim::String),
        prim_seq("data", Prim::U8),
    ],
};

pub static UV_COORDINATE: TypeDef = TypeDef {
    name: "visualization_msgs/msg/UVCoordinate",
    constants: &[],
    fields: &[value("u", Prim::F32), value("v", Prim::F32)],
};

pub static MESH_FILE: TypeDef = TypeDef {
    name: "visualization_msgs/msg/MeshFile",
    constants: &[],
    fields: &[value("filename", Prim::String), prim_seq("data", Prim::U8)],
};

pub static MARKER: TypeDef = TypeDef {
    name: "visualization_msgs/msg/Marker",
    constants: &[
        konst(Prim::I32, "ARROW", "0"),
        konst(Prim::I32, "CUBE", "1"),
        konst(Prim::I32, "SPHERE", "2"),
        konst(Prim::I32, "CYLINDER", "3"),
        konst(Prim::I32, "LINE_STRIP", "4"),
        konst(Prim::I32, "LINE_LIST", "5"),
        konst(Prim::I32, "CUBE_LIST", "6"),
        konst(Prim::I32, "SPHERE_LIST", "7"),
        konst(Prim::I32, "POINTS", "8"),
        konst(Prim::I32, "TEXT_VIEW_FACING", "9"),
        konst(Prim::I32, "MESH_RESOURCE", "10"),
        konst(Prim::I32, "TRIANGLE_LIST", "11"),
        konst(Prim::I32, "ARROW_STRIP", "12"),
        konst(Prim::I32, "ADD", "0"),
        konst(Prim::I32, "MODIFY", "0"),
        konst(Prim::I32, "DELETE", "2"),
        konst(Prim::I32, "DELETEALL", "3"),
    ],
    fields: &[
        nested("header", &HEADER),
        value("ns", Prim::String),
        value("id", Prim::I32),
        value("type", Prim::I32),
        value("action", Prim::I32),
        nested("pose", &POSE),
        nested("scale", &VECTOR3),
        nested("color", &COLOR_RGBA),
        nested("lifetime", &DURATION),
        value("frame_locked", Prim::Bool),
        nested_seq("points", &POINT),
        nested_seq("colors", &COLOR_RGBA),
        value("texture_resource", Prim::String),
        nested("texture", &COMPRESSED_IMAGE),
        nested_seq("uv_coordinates", &UV_COORDINATE),
        value("text", Prim::String),
        value("mesh_resource", Prim::String),
        nested("mesh_file", &MESH_FILE),
        value("mesh_use_embedded_materials", Prim::Bool),
    ],
};

pub static MARKER_ARRAY: TypeDef = TypeDef {
    name: "visualization_msgs/msg/MarkerArray",
    constants: &[],
    fields: &[nested_seq("markers", &MARKER)],
};

pub static KEY_VALUE: TypeDef = TypeDef {
    name: "diagnostic_msgs/msg/KeyValue",
    constants: &[],
    fields: &[value("key", Prim::String), value("value", Prim::String)],
};

pub static DIAGNOSTIC_STATUS: TypeDef = TypeDef {
    name: "diagnostic_msgs/msg/DiagnosticStatus",
    constants: &[
        konst(Prim::Byte, "OK", "0"),
        konst(Prim::Byte, "WARN", "1"),
        konst(Prim::Byte, "ERROR", "2"),
        konst(Prim::Byte, "STALE", "3"),
    ],
    fields: &[
        value("level", Prim::Byte),
        value("name", Prim::String),
        value("message", Prim::String),
        value("hardware_id", Prim::String),
        nested_seq("values", &KEY_VALUE),
    ],
};

pub static DIAGNOSTIC_ARRAY: TypeDef = TypeDef {
    name: "diagnostic_msgs/msg/DiagnosticArray",
    constants: &[],
    fields: &[
        nested("header", &HEADER),
        nested_seq("status", &DIAGNOSTIC_STATUS),
    ],
};

/// Every type defined here, for tests and tools.
pub static ALL: &[&TypeDef] = &[
    &TIME,
    &DURATION,
    &HEADER,
    &COLOR_RGBA,
    &POINT,
    &VECTOR3,
    &QUATERNION,
    &POSE,
    &POSE_STAMPED,
    &TRANSFORM,
    &TRANSFORM_STAMPED,
    &PATH,
    &TF_MESSAGE,
    &COMPRESSED_IMAGE,
    &UV_COORDINATE,
    &MESH_FILE,
    &MARKER,
    &MARKER_ARRAY,
    &KEY_VALUE,
    &DIAGNOSTIC_STATUS,
    &DIAGNOSTIC_ARRAY,
];

/// The type of that name (`pkg/msg/Name`), if defined here.
pub fn by_name(name: &str) -> Option<&'static TypeDef> {
    ALL.iter().copied().find(|t| t.name == name)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hash rmw_zenoh's docs/design.md shows for `std_msgs/msg/String` (its
    /// `chatter` example), from a definition made here only for this check.
    #[test]
    fn the_string_hash_is_the_one_rmw_zenoh_documents() {
        static STRING: TypeDef = TypeDef {
            name: "std_msgs/msg/String",
            constants: &[],
            fields: &[value("data", Prim::String)],
        };
        assert_eq!(
            STRING.type_hash(),
            "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        assert_eq!(STRING.dds_name(), "std_msgs::msg::dds_::String_");
    }

    #[test]
    fn referenced_types_are_sorted_and_exclude_the_type_itself() {
        let json = PATH.hash_json();
        let order: Vec<usize> = [
            "builtin_interfaces/msg/Time\"",
            "geometry_msgs/msg/Point\"",
            "geometry_msgs/msg/Pose\"",
            "geometry_msgs/msg/PoseStamped\"",
            "geometry_msgs/msg/Quaternion\"",
            "std_msgs/msg/Header\"",
        ]
        .iter()
        .map(|n| json.rfind(&format!("\"type_name\": \"{n}")).unwrap())
        .collect();
        assert!(order.windows(2).all(|w| w[0] < w[1]), "{json}");
        assert_eq!(json.matches("nav_msgs/msg/Path").count(), 1);
    }
}
