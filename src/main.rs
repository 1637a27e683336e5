fn main() {
    println!("radiance");
}
